from __future__ import annotations

import numpy as np
import pytest

from scanguard.detect.render import (
    RenderStyle,
    render_extent,
    render_pair,
    render_pairs,
    save_png,
    to_model_input,
    to_rgb,
)
from scanguard.errors import ConfigError, ScanError
from scanguard.geometry import transform_points
from tests.helpers import make_scan, room_segments

WHITE = (255, 255, 255)
RED = (255, 0, 0)
BLUE = (0, 0, 255)
MAGENTA = (255, 0, 255)
EMPTY = np.empty((0, 2))


@pytest.fixture(scope="module")
def room_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    seg = room_segments()
    rng = np.random.default_rng(3)
    prev = make_scan(seg, (0.0, 0.0, 0.0), noise=0.01, rng=rng).points()
    cur = make_scan(seg, (0.3, 0.1, 0.1), noise=0.01, rng=rng).points()
    return prev, cur, np.array([0.25, 0.1, 0.08])


def _colours(img: np.ndarray) -> set[tuple[int, ...]]:
    return {tuple(int(v) for v in c) for c in np.unique(img.reshape(-1, img.shape[-1]), axis=0)}


def test_style_channels_and_yaml_roundtrip(tmp_path):
    assert RenderStyle().channels == 3 and RenderStyle().shape == (256, 256, 3)
    assert RenderStyle.occupancy(64).shape == (64, 64, 2)
    st = RenderStyle.metric(128, resolution=0.1, point_radius=0)
    assert RenderStyle.from_yaml(st.save(tmp_path / "s.yaml")) == st
    with pytest.raises(ConfigError, match="kind"):
        RenderStyle.from_dict({"kind": "fancy"})
    with pytest.raises(ConfigError, match="overlap"):
        RenderStyle.from_dict({"kind": "metric", "overlap": "current"})


def test_paper_known_pixels():
    # Extent: box [0,1]^2, centre 0.5, half 0.5 * 1.25 -> x0 = y0 = -0.125, side 1.25; 100 px.
    st = RenderStyle(size=100, margin=0.25, point_radius=0)
    prev = np.array([[0.0, 0.0], [1.0, 1.0]])
    cur = np.array([[1.0, 0.0], [2.0, 0.5]])  # moved by (-1, 0): lands on (0,0) and (1, 0.5)
    img = render_pair(prev, cur, (-1.0, 0.0, 0.0), st)
    assert img.shape == (100, 100, 3) and img.dtype == np.uint8
    assert render_extent(prev, cur, (-1.0, 0.0, 0.0), st) == pytest.approx((-0.125, -0.125, 1.25))
    # pixel centres at x0 + j * 0.0125: (0, 0) -> col 10, row 90; (1, 1) -> col 90, row 10.
    assert tuple(img[90, 10]) == MAGENTA  # both scans
    assert tuple(img[10, 90]) == RED  # previous only
    assert tuple(img[50, 90]) == BLUE  # current only, y = 0.5 -> row 50
    nonwhite = (img != 255).any(-1)
    assert nonwhite.sum() == 3
    assert _colours(img) == {WHITE, RED, BLUE, MAGENTA}


def test_overlap_current_is_painters_order():
    st = RenderStyle(size=32, point_radius=0, overlap="current")
    pts = np.array([[0.0, 0.0], [1.0, 1.0]])
    img = render_pair(pts, pts, (0, 0, 0), st)
    assert _colours(img) == {WHITE, BLUE}


def test_pose_rotation_is_applied():
    st = RenderStyle(size=64, point_radius=0)
    prev = np.array([[0.0, 1.0], [-1.0, -1.0], [2.0, 0.5]])
    cur = np.array([[1.0, 0.0], [-1.0, 1.0], [0.5, -2.0]])  # prev rotated by -90 deg
    img = render_pair(prev, cur, (0.0, 0.0, np.pi / 2), st)
    assert _colours(img) == {WHITE, MAGENTA}
    assert (img != 255).any(-1).sum() == 3


@pytest.mark.parametrize(("radius", "pixels"), [(0, 1), (1, 5), (1.5, 9), (2, 13)])
def test_marker_disc_sizes(radius, pixels):
    st = RenderStyle.occupancy(64, point_radius=radius, margin=0.2)
    prev = np.array([[0.0, 0.0], [10.0, 10.0]])
    img = render_pair(prev, EMPTY, (0, 0, 0), st)
    assert img[..., 1].max() == 0
    assert (img[..., 0] == 255).sum() == 2 * pixels
    assert set(np.unique(img).tolist()) == {0, 255}


def test_empty_sets_give_blank_images():
    assert (render_pair(EMPTY, EMPTY, (0, 0, 0)) == 255).all()
    assert (render_pair(EMPTY, EMPTY, (0, 0, 0), RenderStyle.metric(64)) == 0).all()
    one = render_pair(EMPTY, np.array([[1.0, 2.0]]), (0, 0, 0), RenderStyle(point_radius=0))
    assert _colours(one) == {WHITE, BLUE} and (one != 255).any(-1).sum() == 1
    nan = np.array([[np.nan, 1.0], [np.inf, 0.0]])
    assert (render_pair(nan, nan, (0, 0, 0)) == 255).all()
    assert render_pairs([], [], np.empty((0, 3)), RenderStyle()).shape == (0, 256, 256, 3)


def test_metric_scale_and_centre():
    st = RenderStyle.metric(64, resolution=0.05, point_radius=0)
    # origin -> centre pixel (32, 32); +x right, +y up; 10 cm = 2 px; beyond 1.6 m is cropped.
    prev = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.25], [5.0, 0.0]])
    img = render_pair(prev, prev, (0.10, 0.0, 0.0), st)
    rows, cols = np.nonzero(img[..., 0])
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(27, 32), (32, 32), (32, 42)]
    rows, cols = np.nonzero(img[..., 1])
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(27, 34), (32, 34), (32, 44)]


def test_batch_matches_single_and_is_deterministic(room_pair):
    prev, cur, pose = room_pair
    poses = np.array([pose, [0, 0, 0], [1.0, -0.5, 0.3]])
    for st in (RenderStyle(), RenderStyle.occupancy(64), RenderStyle.metric(128, point_radius=1.5)):
        batch = render_pairs([prev, prev, cur], [cur, cur, prev], poses, st)
        assert batch.shape == (3, *st.shape)
        for i, (p, c) in enumerate([(prev, cur), (prev, cur), (cur, prev)]):
            np.testing.assert_array_equal(batch[i], render_pair(p, c, poses[i], st))
        np.testing.assert_array_equal(
            batch, render_pairs([prev, prev, cur], [cur, cur, prev], poses, st)
        )


def test_batch_with_empty_and_nan_pairs_matches_single(room_pair):
    prev, cur, pose = room_pair
    with_nan = prev.copy()
    with_nan[::7] = np.nan
    prevs = [prev, EMPTY, with_nan, EMPTY, cur[:1]]
    curs = [EMPTY, cur, cur, EMPTY, cur[:1]]
    poses = np.array([pose, pose, [0.5, 0.0, 1.0], [0, 0, 0], [0, 0, 0]])
    for st in (RenderStyle(size=64), RenderStyle.metric(64, resolution=0.2)):
        batch = render_pairs(prevs, curs, poses, st)
        for i in range(len(prevs)):
            np.testing.assert_array_equal(batch[i], render_pair(prevs[i], curs[i], poses[i], st))
    clean = render_pair(prev[np.isfinite(with_nan).all(1)], cur, poses[2], RenderStyle(size=64))
    np.testing.assert_array_equal(
        batch_nan := render_pair(with_nan, cur, poses[2], RenderStyle(size=64)), clean
    )
    assert (batch_nan != 255).any()


def test_zero_margin_clips_border_points():
    st = RenderStyle.occupancy(10, margin=0.0, point_radius=0)
    img = render_pair(np.array([[0.0, 0.0], [1.0, 1.0]]), EMPTY, (0, 0, 0), st)
    rows, cols = np.nonzero(img[..., 0])
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(0, 9), (9, 0)]


def test_laserscan_input_equals_points():
    seg = room_segments()
    a, b = make_scan(seg, (0, 0, 0)), make_scan(seg, (0.2, 0, 0.05))
    np.testing.assert_array_equal(
        render_pair(a, b, (0.2, 0, 0.05)), render_pair(a.points(), b.points(), (0.2, 0, 0.05))
    )


def test_occupancy_equals_paper_channels(room_pair):
    prev, cur, pose = room_pair
    paper = render_pair(prev, cur, pose, RenderStyle(size=128))
    occ = render_pair(prev, cur, pose, RenderStyle.occupancy(128))
    np.testing.assert_array_equal(to_rgb(occ), paper)
    # previous = pixels that are not pure blue nor white; current = not pure red nor white
    assert ((occ[..., 0] == 255) == (paper[..., 0] == 255) & (paper[..., 1] == 0)).all()


def test_bad_inputs_raise():
    with pytest.raises(ScanError, match="previous"):
        render_pair(np.zeros((4, 3)), EMPTY, (0, 0, 0))
    with pytest.raises(ScanError, match="pose"):
        render_pair(EMPTY, EMPTY, (0, 0))
    with pytest.raises(ScanError, match="must match"):
        render_pairs([EMPTY], [EMPTY, EMPTY], np.zeros((1, 3)), RenderStyle())


def test_to_model_input():
    imgs = np.zeros((2, 4, 5, 3), dtype=np.uint8)
    imgs[1, 2, 3] = (255, 51, 0)
    x = to_model_input(imgs)
    assert x.shape == (2, 3, 4, 5) and x.dtype == np.float32
    assert x[1, :, 2, 3] == pytest.approx([1.0, 0.2, 0.0])
    assert x.sum() == pytest.approx(1.2)
    assert to_model_input(imgs[1]).shape == (1, 3, 4, 5)


def test_save_png_roundtrip(tmp_path, room_pair):
    import matplotlib.image as mpimg

    prev, cur, pose = room_pair
    img = render_pair(prev, cur, pose, RenderStyle(size=96))
    path = save_png(tmp_path / "a" / "pair.png", img)
    back = (mpimg.imread(path) * 255).round().astype(np.uint8)
    np.testing.assert_array_equal(back[..., :3], img)
    occ = render_pair(prev, cur, pose, RenderStyle.occupancy(96))
    back2 = (mpimg.imread(save_png(tmp_path / "occ.png", occ)) * 255).round().astype(np.uint8)
    np.testing.assert_array_equal(back2[..., :3], img)
    assert list(tmp_path.rglob(".*")) == []  # no temporary files left
    with pytest.raises(ConfigError, match=r"bad\.png"):
        save_png(tmp_path / "bad.png", np.zeros((4, 4), dtype=np.float32))


def _classes(img: np.ndarray) -> np.ndarray:
    """0 = white, 1 = red-dominant ink, 2 = blue-dominant ink (tolerates anti-aliasing)."""
    im = img[..., :3].astype(int)
    ink = im.min(-1) < 128
    out = np.zeros(im.shape[:2], dtype=int)
    out[ink & (im[..., 0] >= im[..., 2])] = 1
    out[ink & (im[..., 2] > im[..., 0])] = 2
    return out


@pytest.mark.parametrize(
    ("radius", "marker", "marker_px", "min_iou"), [(1.0, "o", 2.0, 0.95), (1.5, "s", 3.0, 0.99)]
)
def test_paper_style_matches_matplotlib(room_pair, radius, marker, marker_px, min_iou):
    """Same pair plotted by matplotlib (Agg, 256x256 px, no axes, same extent and colours).

    Metric: IoU of the ink (non-white) masks, and the agreement of the ink colour class (red or
    blue) over the union of both masks. overlap="current" reproduces matplotlib's draw order.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    prev, cur, pose = room_pair
    st = RenderStyle(point_radius=radius, overlap="current")
    ours = render_pair(prev, cur, pose, st)
    x0, y0, side = render_extent(prev, cur, pose, st)
    moved = transform_points(pose, cur)
    fig = plt.figure(figsize=(2.56, 2.56), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    ax.set_xlim(x0, x0 + side)
    ax.set_ylim(y0, y0 + side)
    ms = marker_px * 72 / 100
    ax.plot(prev[:, 0], prev[:, 1], marker, color=(1, 0, 0), ms=ms, mew=0, ls="none")
    ax.plot(moved[:, 0], moved[:, 1], marker, color=(0, 0, 1), ms=ms, mew=0, ls="none")
    fig.canvas.draw()
    ref = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    assert ref.shape == ours.shape
    a, b = _classes(ours), _classes(ref)
    union = (a > 0) | (b > 0)
    iou = ((a > 0) & (b > 0)).sum() / union.sum()
    class_agreement = (a[union] == b[union]).mean()
    assert union.sum() > 1500  # the scans really cover the image
    assert iou > min_iou
    assert class_agreement > min_iou - 0.03


# sha256 prefixes of `render_pairs` output for the pairs below, recorded with the pure-numpy
# renderer before the numba kernel replaced it: the kernel must keep every byte.
_PINNED = {
    "paper": (RenderStyle(), "345c6ab03acb85e068df"),
    "paper_current_r1.5": (
        RenderStyle(overlap="current", point_radius=1.5),
        "12ced8410f2ecd7e5f92",
    ),
    "occ128": (RenderStyle.occupancy(128), "6f507df4c05a360e388d"),
    "occ64_r2": (RenderStyle.occupancy(64, point_radius=2), "e62b8546b4d9e1f6efcf"),
    "metric256": (RenderStyle.metric(256), "df08db53eda30a75a27d"),
    "metric128_r1.5": (
        RenderStyle.metric(128, resolution=0.1, point_radius=1.5),
        "33d03b529e5eb9a87d0d",
    ),
    "paper64_m0_r0": (RenderStyle(size=64, margin=0.0, point_radius=0), "0ba0f04c6d42b1026af2"),
}


@pytest.mark.parametrize("name", sorted(_PINNED))
def test_images_are_pinned(room_pair, name):
    import hashlib

    prev, cur, pose = room_pair
    poses = np.array([pose, [0, 0, 0], [1.0, -0.5, 0.3], [-0.4, 0.2, -2.0]])
    prevs = [prev, prev, cur, prev[::3].astype(np.float64)]
    curs = [cur, cur, prev, cur[5:]]
    style, digest = _PINNED[name]
    batch = render_pairs(prevs, curs, poses, style)
    assert hashlib.sha256(batch.tobytes()).hexdigest()[:20] == digest
    for i in range(len(prevs)):
        np.testing.assert_array_equal(batch[i], render_pair(prevs[i], curs[i], poses[i], style))


def test_kernel_matches_numpy_reference():
    """The numba kernel against the pure-numpy reference on random scenes, byte for byte."""
    from scanguard.detect.render_reference import render_pairs_numpy

    rng = np.random.default_rng(11)
    prevs, curs = [], []
    for i in range(24):
        n, m = rng.integers(0, 400, size=2)
        scale = 10.0 ** rng.uniform(-3, 2)  # tiny to 100 m scenes (tiny: coincident points)
        p = rng.normal(size=(n, 2)) * scale
        c = rng.normal(size=(m, 2)) * scale
        if i % 5 == 0 and n:
            p[rng.integers(0, n, size=3)] = [np.nan, np.inf][i % 2]
        prevs.append(p.astype(np.float32) if i % 3 == 0 else p)
        curs.append(c)
    poses = np.column_stack([rng.normal(size=(24, 2)), rng.uniform(-np.pi, np.pi, 24)])
    for st in (
        RenderStyle(size=96),
        RenderStyle(size=64, overlap="current", point_radius=2),
        RenderStyle(size=50, margin=0.0, point_radius=1.5),
        RenderStyle.occupancy(32, point_radius=0),
        RenderStyle.metric(80, resolution=0.07, point_radius=1),
    ):
        ours = render_pairs(prevs, curs, poses, st)
        ref = render_pairs_numpy(prevs, curs, poses, st)
        np.testing.assert_array_equal(ours, ref)
        for i in (0, 5, 17):
            e = render_extent(prevs[i], curs[i], poses[i], st)
            assert e == pytest.approx(tuple(_extent_reference(prevs[i], curs[i], poses[i], st)))


def _extent_reference(prev, cur, pose, st):
    from scanguard.detect.render_reference import Prepared

    return Prepared([prev], [cur], np.asarray(pose, dtype=float)[None], st).extents[0]


def test_multiscale_stacks_occupancy_and_metric_views(room_pair):
    prev, cur, pose = room_pair
    st = RenderStyle.multiscale(64, scales=(0.05, 0.2))
    assert st.channels == 6 and st.shape == (64, 64, 6)
    assert RenderStyle.from_dict(st.model_dump()) == st
    poses = np.array([pose, [0.0, 0.0, 0.0]])
    img = render_pairs([prev, prev], [cur, cur], poses, st)
    assert img.shape == (2, 64, 64, 6)
    views = [RenderStyle.occupancy(64), RenderStyle.metric(64, 0.05), RenderStyle.metric(64, 0.2)]
    for v, view in enumerate(views):
        np.testing.assert_array_equal(
            img[..., 2 * v : 2 * v + 2], render_pairs([prev, prev], [cur, cur], poses, view)
        )
    np.testing.assert_array_equal(img[0], render_pair(prev, cur, pose, st))
    # Known answer: a point 0.5 m ahead and a 10 cm shift of the current scan -> 2 px apart in
    # the 0.05 m/px view (columns 42 / 44) but the same pixel at 0.2 m/px (0.5 m = 2.5 px and
    # 0.6 m = 3 px right of the centre pixel 32, both floor(... + 0.5) = 35).
    pt = np.array([[0.5, 0.0]])
    one = render_pair(pt, pt, (0.1, 0.0, 0.0), RenderStyle.multiscale(64, point_radius=0))
    assert np.flatnonzero(one[32, :, 2]).tolist() == [42]
    assert np.flatnonzero(one[32, :, 3]).tolist() == [44]
    assert np.flatnonzero(one[32, :, 4]).tolist() == [35]
    assert np.flatnonzero(one[32, :, 5]).tolist() == [35]
    with pytest.raises(ConfigError, match="scales"):
        RenderStyle.from_dict({"kind": "multiscale", "scales": [0.05, -1.0]})


def test_multiscale_matches_numpy_reference(room_pair):
    from scanguard.detect.render_reference import render_pairs_numpy

    prev, cur, pose = room_pair
    poses = np.array([pose, [1.0, -0.5, 0.3]])
    st = RenderStyle.multiscale(48, scales=(0.1,))
    assert st.channels == 4
    np.testing.assert_array_equal(
        render_pairs([prev, cur], [cur, prev], poses, st),
        render_pairs_numpy([prev, cur], [cur, prev], poses, st),
    )
