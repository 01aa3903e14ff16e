"""Correlative scan-to-map matcher: known offsets, exactness of branch-and-bound, covariance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.errors import ConfigError, MatchingError
from scanguard.geometry import inverse, transform_points
from scanguard.matching import MATCHERS, get_matcher
from scanguard.matching import _correlative as _k
from scanguard.matching.config import CorrelativeConfig
from scanguard.matching.correlative import (
    correlative_match,
    match_to_map,
    second_peak,
    theta_step_for,
)
from scanguard.matching.likelihood import LikelihoodGrid, outline_points, thin_points
from scanguard.scan import SensorInfo
from tests.helpers import corridor_segments, raycast, room_segments

SENSOR = SensorInfo(
    name="360-beam",
    n_beams=360,
    angle_min=-np.pi,
    angle_increment=2 * np.pi / 360,
    range_min=0.1,
    range_max=12.0,
    rate_hz=10.0,
)
TRUE = np.array([0.4, -0.3, 0.15])
OFFSET = np.array([0.17, -0.11, 0.08])


def scan_points(segments: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Sensor-frame points of a 360-beam scan taken at ``pose``."""
    r = raycast(segments, pose, SENSOR).astype(np.float64)
    a = SENSOR.angle_min + SENSOR.angle_increment * np.arange(SENSOR.n_beams)
    ok = np.isfinite(r)
    return np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])


def local_map(segments: np.ndarray, n: int = 10) -> np.ndarray:
    """Map-frame points of ``n`` scans along a short path (a 10-scan local map)."""
    poses = [np.array([0.12 * i, 0.05 * i - 0.2, 0.03 * i]) for i in range(n)]
    return np.vstack([transform_points(p, scan_points(segments, p)) for p in poses])


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray]:
    segs = room_segments()
    return local_map(segs), scan_points(segs, TRUE)


@pytest.mark.parametrize("resolution", [0.01, 0.02, 0.05, 0.1])
@pytest.mark.parametrize("levels", [1, 2, 3, 4])
def test_known_offset_recovered(room, resolution, levels):
    mp, src = room
    # a window just larger than the offset keeps the exhaustive (levels=1, 1 cm) case fast
    cfg = CorrelativeConfig(
        resolution=resolution,
        levels=levels,
        sigma=max(0.05, resolution),
        window_xy=0.2,
        window_theta=0.1,
    )
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = TRUE - OFFSET
    res = correlative_match(src, grid, init, cfg)
    assert res.found
    assert res.theta_step == pytest.approx(theta_step_for(src, resolution))
    # the pose lives on the lattice around the initial pose: within one cell of the truth; in
    # theta the snapping of points to cell centres trades rotation against translation, and
    # the best lattice pose is up to ~1.2 steps off (measured: 1.16 at 1 cm, 1.03 at 5 cm)
    assert abs(res.pose[0] - TRUE[0]) <= resolution + 1e-9
    assert abs(res.pose[1] - TRUE[1]) <= resolution + 1e-9
    assert abs(res.pose[2] - TRUE[2]) <= 1.25 * res.theta_step
    # so every point is within ~1.5 cells of where the true pose puts it
    moved = transform_points(res.pose, src) - transform_points(TRUE, src)
    assert np.max(np.hypot(moved[:, 0], moved[:, 1])) <= 1.6 * resolution
    assert res.score == pytest.approx(grid.score(src, res.pose), abs=1e-6)
    assert res.score > 0.8
    assert res.score > grid.score(src, init) + 0.3


def _offsets(grid, src, cfg):
    step = theta_step_for(src, grid.resolution)
    n = math.ceil(cfg.window_theta / step - 1e-9)
    return np.arange(-n, n + 1) * step


def _lattice(grid, src, init, cfg):
    ix, iy = _k.discretise(src, *init, _offsets(grid, src, cfg), *grid.origin, grid.resolution)
    w = math.ceil(cfg.window_xy / grid.resolution - 1e-9)
    return ix, iy, w


def _merged(ix, iy):
    """Runs of equal consecutive cells per row, as plain Python (the reference)."""
    rows = []
    for a, b in zip(ix, iy, strict=True):
        cells: list[list[int]] = []
        for x, y in zip(a.tolist(), b.tolist(), strict=True):
            if cells and cells[-1][:2] == [x, y]:
                cells[-1][2] += 1
            else:
                cells.append([x, y, 1])
        rows.append(cells)
    return rows


def test_branch_and_bound_equals_brute_force():
    rng = np.random.default_rng(7)
    mp = rng.uniform(-3, 3, size=(400, 2))
    true = np.array([0.05, -0.07, 0.04])
    src = transform_points(inverse(true), mp[:150])
    src += rng.normal(0, 0.01, src.shape)
    src = np.vstack([src, rng.uniform(-3, 3, size=(50, 2))])  # clutter
    cfg = CorrelativeConfig(resolution=0.05, levels=4, window_xy=0.4, window_theta=0.1)
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = np.array([0.1, 0.05, -0.02])
    ix, iy, w = _lattice(grid, src, init, cfg)
    _, _, _, brute, n_brute = _k.brute_force(grid.stack, grid.pad, ix, iy, w)
    res = correlative_match(src, grid, init, cfg)
    assert res.score * len(src) == pytest.approx(brute, rel=1e-12, abs=1e-9)
    assert res.n_evaluated < n_brute
    # every coarse level bounds the finest one from above
    for h in range(1, grid.levels):
        fine = grid.level(0)
        coarse = grid.level(h)
        assert np.all(coarse >= fine)


def test_second_peak_is_the_exact_best_outside_the_disc_and_finds_the_alias():
    rng = np.random.default_rng(3)
    # posts every 1.0 m along x (doors along a corridor): a match one period off scores alike
    posts = np.vstack(
        [np.array([1.0 * i, 0.0]) + rng.normal(0, 0.03, (12, 2)) for i in range(-6, 7)]
    )
    walls = np.column_stack([np.linspace(-7, 7, 300), np.full(300, 1.2)])
    mp = np.vstack([posts, walls])
    true = np.array([0.0, 0.0, 0.0])
    src = transform_points(inverse(true), mp[np.abs(mp[:, 0]) < 3.0])
    cfg = CorrelativeConfig(resolution=0.05, levels=3, window_xy=1.4, window_theta=0.05)
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = np.array([0.1, 0.05, 0.0])
    best = correlative_match(src, grid, init, cfg)
    assert best.found and np.hypot(*(best.pose[:2] - true[:2])) < 0.08
    alt = second_peak(src, grid, init, best, cfg, radius=0.5, min_ratio=0.5)
    assert alt.found
    assert np.hypot(*(alt.pose[:2] - best.pose[:2])) >= 0.5
    assert abs(abs(alt.pose[0] - best.pose[0]) - 1.0) < 0.15  # one post along
    assert 0.7 < alt.score / best.score <= 1.0
    # exact: the brute-force best of every lattice pose outside the disc
    ix, iy, w = _lattice(grid, src, init, cfg)
    r = grid.resolution
    cx, cy = round((best.pose[0] - init[0]) / r), round((best.pose[1] - init[1]) / r)
    top = max(
        _k._sum_at(grid.stack[0], grid.pad, ix, iy, k, dx, dy)
        for k in range(ix.shape[0])
        for dx in range(-w, w + 1)
        for dy in range(-w, w + 1)
        if (dx - cx) ** 2 + (dy - cy) ** 2 > (0.5 / r) ** 2
    )
    assert alt.score * len(src) == pytest.approx(top, rel=1e-12, abs=1e-9)
    # nothing that high elsewhere: not found
    assert not second_peak(src, grid, init, best, cfg, radius=0.5, min_ratio=1.01).found


def test_offset_outside_window_not_found_at_truth(room):
    mp, src = room
    cfg = CorrelativeConfig(window_xy=0.1, window_theta=0.05)
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = TRUE - np.array([0.5, 0.0, 0.0])  # 0.5 m off, window 0.1 m
    res = correlative_match(src, grid, init, cfg)
    at_truth = grid.score(src, TRUE)
    assert abs(res.pose[0] - TRUE[0]) > 0.3
    assert res.score < at_truth - 0.1
    # the best reachable pose is pushed against the window border towards the truth
    assert res.pose[0] - init[0] == pytest.approx(0.1, abs=1e-9)


def test_min_score_not_found():
    segs = room_segments()
    grid = LikelihoodGrid.from_points(local_map(segs), CorrelativeConfig())
    src = scan_points(segs, TRUE)
    cfg = CorrelativeConfig(min_score=0.99, window_xy=0.1, window_theta=0.05)
    res = correlative_match(src, grid, TRUE + np.array([1.0, 0.0, 0.0]), cfg)
    assert not res.found
    np.testing.assert_allclose(res.pose, TRUE + np.array([1.0, 0.0, 0.0]))
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)
    mr, _ = match_to_map(src, grid, TRUE + np.array([1.0, 0.0, 0.0]), cfg)
    assert not mr.ok and "min_score" in mr.reason


def test_covariance_positive_definite(room):
    mp, src = room
    grid = LikelihoodGrid.from_points(mp, CorrelativeConfig())
    res = correlative_match(src, grid, TRUE - OFFSET)
    cov = res.covariance
    np.testing.assert_allclose(cov, cov.T)
    ev = np.linalg.eigvalsh(cov)
    assert np.all(ev > 0)
    assert cov[0, 0] >= 0.02**2 / 12 and cov[2, 2] >= res.theta_step**2 / 12
    assert math.sqrt(cov[0, 0]) < 0.05 and math.sqrt(cov[1, 1]) < 0.05


def test_corridor_covariance_large_along_axis():
    segs = corridor_segments(length=60.0, width=2.0)
    pose = np.array([0.3, 0.1, 0.02])
    mp = np.vstack(
        [transform_points(p, scan_points(segs, p)) for p in [pose, pose + np.array([1.0, 0, 0])]]
    )
    src = scan_points(segs, pose)
    cfg = CorrelativeConfig(resolution=0.02)
    grid = LikelihoodGrid.from_points(mp, cfg)
    res = correlative_match(src, grid, pose + np.array([0.05, -0.04, 0.01]), cfg)
    assert abs(res.pose[1] - pose[1]) <= 0.02 + 1e-9
    cov = res.covariance
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # along the corridor (x) the response is flat: the variance is that of the whole
    # neighbourhood; across (y) it is pinned by the walls
    assert cov[0, 0] > 10 * cov[1, 1]
    assert cov[0, 0] > 0.03**2


def test_match_to_map_refines_below_one_cell(room):
    mp, src = room
    cfg = CorrelativeConfig(resolution=0.05, sigma=0.05)
    grid = LikelihoodGrid.from_points(mp, cfg)
    mr, corr = match_to_map(src, grid, TRUE - OFFSET, cfg)
    assert mr.ok and mr.method == "correlative+plicp"
    err_corr = np.hypot(*(corr.pose[:2] - TRUE[:2]))
    err = np.hypot(*(mr.pose[:2] - TRUE[:2]))
    assert err < 0.005 < 0.05
    assert err <= err_corr
    assert abs(mr.pose[2] - TRUE[2]) < 1e-3
    plain, _ = match_to_map(src, grid, TRUE - OFFSET, cfg.model_copy(update={"refine": False}))
    assert plain.method == "correlative" and plain.ok
    np.testing.assert_allclose(plain.pose, corr.pose)


def test_registry_matcher(room):
    segs = room_segments()
    tgt = scan_points(segs, np.zeros(3))
    src = scan_points(segs, TRUE)
    m = get_matcher("correlative")
    assert "correlative" in MATCHERS and m.name == "correlative"
    r = m(src, tgt, TRUE - OFFSET)
    assert r.ok
    assert np.hypot(*(r.pose[:2] - TRUE[:2])) < 0.02
    bad = m(src[:3], tgt, None)
    assert not bad.ok and "too few" in bad.reason


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": -0.1}, "resolution"),
        ({"levels": 0}, "levels"),
        ({"sigma": 0.0}, "sigma"),
        ({"window_xy": float("nan")}, "window_xy"),
        ({"theta_step": -1.0}, "theta_step"),
    ],
)
def test_bad_config(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        CorrelativeConfig(**kwargs)


def test_bad_input(room):
    mp, src = room
    cfg = CorrelativeConfig()
    with pytest.raises(MatchingError, match="no finite point"):
        LikelihoodGrid.from_points(np.zeros((0, 2)), cfg)
    with pytest.raises(MatchingError, match="no finite point"):
        LikelihoodGrid.from_points(np.full((5, 2), np.nan), cfg)
    with pytest.raises(MatchingError, match="too large"):
        LikelihoodGrid.from_points(np.array([[0.0, 0.0], [1e6, 1e6]]), cfg)
    grid = LikelihoodGrid.from_points(mp, cfg)
    with pytest.raises(MatchingError, match="no finite point"):
        correlative_match(np.zeros((0, 2)), grid, TRUE)
    with pytest.raises(MatchingError, match="no finite point"):
        correlative_match(np.full((4, 2), np.inf), grid, TRUE)
    with pytest.raises(MatchingError, match="initial pose must be finite"):
        correlative_match(src, grid, [0.0, np.nan, 0.0])
    with pytest.raises(MatchingError, match="shape"):
        correlative_match(src, grid, [0.0, 0.0])
    with pytest.raises(MatchingError, match="window_xy"):
        correlative_match(src, grid, TRUE, window_xy=-1.0)
    with pytest.raises(ConfigError, match="resolution"):
        correlative_match(src, grid, TRUE, CorrelativeConfig(resolution=0.05))
    with pytest.raises(ConfigError, match="levels"):
        correlative_match(src, grid, TRUE, CorrelativeConfig(levels=5))
    # NaN rows are dropped, not fatal
    noisy = np.vstack([src, [[np.nan, 1.0]]])
    assert correlative_match(noisy, grid, TRUE).n_source == len(src)


@pytest.mark.parametrize(("res", "sigma"), [(0.05, 0.05), (0.05, 0.08), (0.03, 0.05)])
def test_table_is_the_max_of_per_point_kernels(res, sigma):
    """One exp per cell (from the nearest point's squared distance) equals the max over points
    of each point's kernel: the definition of the table (numpy's exp may differ from libm's
    in the last bit, hence the tolerance). Windows of one and two blocks of columns; points
    beside the grid and across its borders count where they reach."""
    rng = np.random.default_rng(11)
    pts = np.vstack(
        [
            rng.uniform(-1.0, 1.0, size=(60, 2)),
            [[0.0, 0.0], [0.0, 0.0], [-1.32, 0.1], [1.4, -1.25], [5.0, 5.0], [-4.0, 0.0]],
        ]
    )
    cutoff = 3 * sigma
    x0, y0, nx, ny = -1.3, -1.2, 52, 50
    table = _k.likelihood_stack(pts, x0, y0, res, nx, ny, sigma, cutoff, 1)[0]
    xs = x0 + (np.arange(nx) + 0.5) * res
    ys = y0 + (np.arange(ny) + 0.5) * res
    d2 = (xs[None, None, :] - pts[:, 0, None, None]) ** 2 + (
        ys[None, :, None] - pts[:, 1, None, None]
    ) ** 2
    kernel = np.where(d2 <= cutoff**2, np.exp(-d2 * (0.5 / sigma**2)), 0.0).astype(np.float32)
    assert table.dtype == np.float32
    expected = kernel.max(axis=0)
    assert np.array_equal(table == 0, expected == 0)
    np.testing.assert_allclose(table, expected, rtol=1e-6, atol=0)


@pytest.mark.parametrize("levels", [1, 2, 4])
def test_likelihood_stack_is_the_padded_max_pyramid_of_the_table(levels):
    """Level 0 is the table (after the zero padding); level h is the max of the 2**h x 2**h
    table cells from each cell up, cells off the table counting as 0 (numpy, cell by cell)."""
    rng = np.random.default_rng(12)
    pts = rng.uniform(-1.0, 1.0, size=(40, 2))
    res, sigma, cutoff = 0.05, 0.05, 0.15
    x0, y0, nx, ny = -1.3, -1.2, 53, 49
    table = _k.likelihood_stack(pts, x0, y0, res, nx, ny, sigma, cutoff, 1)[0]
    stack = _k.likelihood_stack(pts, x0, y0, res, nx, ny, sigma, cutoff, levels)
    pad = (1 << (levels - 1)) - 1
    assert stack.shape == (levels, ny + pad, nx + pad)
    assert np.array_equal(stack[0, pad:, pad:], table)
    padded = np.zeros((ny + 2 * pad, nx + 2 * pad), dtype=np.float32)
    padded[pad : pad + ny, pad : pad + nx] = table
    for h in range(levels):
        size = 1 << h
        expected = np.array(
            [
                [padded[a : a + size, b : b + size].max() for b in range(nx + pad)]
                for a in range(ny + pad)
            ]
        )
        assert np.array_equal(stack[h], expected), h


def test_bounds_kernel_equals_numpy():
    """The one-pass bounding box the grid is built from is numpy's min / max exactly."""
    rng = np.random.default_rng(5)
    for n in (1, 2, 17, 4000):
        pts = rng.normal(0.0, 30.0, size=(n, 2)) + rng.uniform(-1e5, 1e5, size=2)
        xmin, ymin, xmax, ymax = _k.bounds(pts)
        assert (xmin, ymin) == tuple(pts.min(axis=0))
        assert (xmax, ymax) == tuple(pts.max(axis=0))


def test_grid_origin_and_shape_from_the_bounds(room):
    """The grid's origin is the points' minimum less the margin, as before the kernel."""
    mp, _ = room
    cfg = CorrelativeConfig(resolution=0.05, sigma=0.05)
    grid = LikelihoodGrid.from_points(mp, cfg)
    margin = 3 * 0.05 + 0.05
    lo = mp.min(axis=0) - margin
    hi = mp.max(axis=0) + margin
    assert grid.origin == (float(lo[0]), float(lo[1]))
    assert grid.shape == (
        math.ceil((hi[1] - lo[1]) / 0.05) + 1,
        math.ceil((hi[0] - lo[0]) / 0.05) + 1,
    )


@pytest.mark.parametrize("resolution", [0.05, 0.1])
def test_merged_runs_search_exactly_as_every_point(room, resolution):
    """Consecutive points in one cell scored once with their count: the same search, bit for bit."""
    mp, src = room
    dense = np.repeat(src, 3, axis=0) + np.random.default_rng(3).normal(0, 0.004, (3 * len(src), 2))
    cfg = CorrelativeConfig(
        resolution=resolution, levels=4, window_xy=0.5, window_theta=0.2, min_score=0.05
    )
    grid = LikelihoodGrid.from_points(mp, cfg)
    # the exactness rests on the table's values: 0, or float32s of exponent >= -7
    table = grid.table
    assert table[table > 0].min() >= 2.0**-7
    init = TRUE - OFFSET
    ix, iy, w = _lattice(grid, dense, init, cfg)
    offsets = _offsets(grid, dense, cfg)
    mx, my, wt, cnt = _k.discretise_runs(dense, *init, offsets, *grid.origin, grid.resolution)
    assert cnt.max() < ix.shape[1]  # something was merged
    for k, cells in enumerate(_merged(ix, iy)):
        assert cnt[k] == len(cells)
        got = np.column_stack([mx[k, : cnt[k]], my[k, : cnt[k]], wt[k, : cnt[k]]])
        np.testing.assert_array_equal(got, np.array(cells, dtype=np.float64))
    ones = np.ones(ix.shape, dtype=np.float64)
    every = np.full(ix.shape[0], ix.shape[1], dtype=np.int64)
    for threshold in (0.0, 0.3 * len(dense)):
        merged = _k.branch_and_bound(grid.stack, grid.pad, mx, my, wt, cnt, w, 4, threshold)
        each = _k.branch_and_bound(grid.stack, grid.pad, ix, iy, ones, every, w, 4, threshold)
        assert merged == each  # the pose, the sum (exact), the evaluations, found
        _, _, _, brute, _ = _k.brute_force(grid.stack, grid.pad, ix, iy, w)
        if merged[5]:
            assert merged[3] == brute  # and the per-point sum, in another order, the same


def _outline_reference(p, inc, spacing, max_gap=0.5, gap_beams=10.0):
    """The vectorised numpy formulation the kernel replaced (the same operations in order)."""
    a, b = p[:-1], p[1:]
    d = np.hypot(*(b - a).T)
    r = np.minimum(np.hypot(*a.T), np.hypot(*b.T))
    join = (d > spacing) & (d <= np.minimum(max_gap, gap_beams * r * abs(inc)))
    k = np.ceil(d[join] / spacing).astype(np.int64) - 1
    seg = np.repeat(np.flatnonzero(join), k)
    first = np.cumsum(k) - k
    t = (np.arange(int(k.sum())) - np.repeat(first, k) + 1) / np.repeat(k + 1, k)
    return np.concatenate([p, a[seg] + t[:, None] * (b[seg] - a[seg])])


def test_outline_fills_the_gaps_it_should_and_no_other():
    inc = 0.01
    # 0.2 m apart at 2 m (within 10 beams x 2 m x 0.01 = 0.2 m): three points at 5 cm
    p = np.array([[2.0, 0.0], [2.0, 0.2], [2.0, 0.23], [2.0, 0.93], [2.0, 0.95]])
    out = outline_points(p, inc, spacing=0.05)
    np.testing.assert_array_equal(out[: len(p)], p)  # the hits first, untouched
    np.testing.assert_allclose(out[len(p) :], [[2.0, 0.05], [2.0, 0.10], [2.0, 0.15]], atol=1e-12)
    # 3 cm (not above the spacing) and 0.7 m (beyond max_gap, and 10 beams) stay open
    assert len(out) == len(p) + 3
    assert len(outline_points(p, inc, spacing=0.05, gap_beams=5.0)) == len(p)  # 0.1 m reach
    assert len(outline_points(p[:1], inc, spacing=0.05)) == 1
    assert len(outline_points(p, inc, spacing=0.0)) == len(p)


def test_outline_is_the_vectorised_formula_bit_for_bit():
    rng = np.random.default_rng(8)
    for n in (2, 3, 40, 720):
        ang = np.sort(rng.uniform(-np.pi, np.pi, n))
        rng_m = rng.uniform(0.5, 12.0) + rng.normal(0, 0.3, n).cumsum() * 0.1
        p = np.column_stack([np.abs(rng_m) * np.cos(ang), np.abs(rng_m) * np.sin(ang)])
        for spacing in (0.03, 0.05, 0.2):
            got = outline_points(p, -2 * np.pi / n, spacing=spacing, max_gap=1.0)
            want = _outline_reference(p, -2 * np.pi / n, spacing, max_gap=1.0)
            assert got.shape == want.shape and got.tobytes() == want.tobytes()


def test_thin_keeps_the_first_point_of_each_lattice_square():
    # squares of 0.1 m: (0, 0) holds the first two, (-1, 0) the third, (0, 0) again the fourth
    pts = np.array([[0.05, 0.05], [0.01, 0.09], [-0.01, 0.05], [0.099, 0.0], [0.25, -0.31]])
    kept = thin_points(pts, 0.1)
    np.testing.assert_array_equal(kept, pts[[0, 2, 4]])
    assert thin_points(pts, 0.0) is pts  # 0: every point, the same array
    assert thin_points(pts, 0.001) is pts  # nothing dropped: the same array


def test_thin_drops_only_points_near_a_kept_one_and_agrees_with_unique():
    rng = np.random.default_rng(3)
    pts = np.round(rng.uniform(-7.0, 5.0, (4000, 2)) * 40) / 40  # many repeats at 2.5 cm
    cell = 0.05
    kept = thin_points(pts, cell)
    squares = np.floor(pts / cell).astype(np.int64)
    first = np.sort(np.unique(squares, axis=0, return_index=True)[1])
    np.testing.assert_array_equal(kept, pts[first])
    d = np.hypot(*(pts[:, None, :] - kept[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert d.max() <= cell * math.sqrt(2)


def test_thin_hash_table_equals_the_bitmap():
    rng = np.random.default_rng(4)
    pts = np.round(rng.uniform(-3.0, 3.0, (3000, 2)) * 30) / 30
    np.testing.assert_array_equal(_k.thin(pts, 0.05), _k._thin_hashed(pts, 0.05))
    # a lattice far too large for a bitmap (1e12 squares) takes the hash table
    far = np.array([[0.0, 0.0], [1e4, 1e4], [0.001, 0.002], [1e4 + 0.001, 1e4], [-1e4, 3.0]])
    np.testing.assert_array_equal(_k.thin(far, 0.01), [0, 1, 4])
