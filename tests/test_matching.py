"""Known-answer tests of scanguard.matching on synthetic rooms and corridors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from scanguard.errors import MatchingError
from scanguard.geometry import compose, transform_points
from scanguard.matching import (
    MATCHERS,
    ICPConfig,
    Matcher,
    MatchResult,
    _grid,
    as_points,
    get_matcher,
    icp_point_to_line,
    icp_point_to_point,
    register_matcher,
)
from scanguard.matching.reference import icp_point_to_point_reference
from scanguard.scan import SensorInfo
from tests.helpers import RPLIDAR, corridor_segments, make_scan, room_segments

ROOM = room_segments()
P0 = np.array([0.3, 0.2, 0.1])
STEPS = [
    (0.05, 0.0, math.radians(1.0)),
    (0.05, 0.02, math.radians(4.0)),
    (0.3, 0.0, math.radians(10.0)),
    (-0.2, 0.15, math.radians(-7.0)),
    (0.0, -0.3, math.radians(5.0)),
]


def _pair(step, noise=0.003, seed=0, segments=ROOM, start=P0):
    rng = np.random.default_rng(seed)
    target = make_scan(segments, start, noise=noise, rng=rng)
    source = make_scan(segments, compose(start, step), noise=noise, rng=rng)
    return source, target


def _err(pose, truth):
    d = np.asarray(pose) - np.asarray(truth)
    return math.hypot(d[0], d[1]), abs(math.degrees((d[2] + math.pi) % (2 * math.pi) - math.pi))


@pytest.mark.parametrize("icp", [icp_point_to_point, icp_point_to_line])
@pytest.mark.parametrize("step", STEPS)
def test_default_icp_recovers_known_motion_in_room(icp, step):
    source, target = _pair(step, seed=int(abs(step[2]) * 1000))
    r = icp(source, target)
    dt, dth = _err(r.pose, step)
    assert dt < 0.01 and dth < 0.2, (r.pose, step, r.iterations)
    assert r.iterations <= 20
    assert r.n_source == int(source.valid.sum()) and r.n_target == int(target.valid.sum())
    assert r.inlier_ratio > 0.9 and r.median_residual < 0.02


def test_matches_numpy_svd_reference_exactly():
    for step in STEPS[:3]:
        source, target = _pair(step, noise=0.01, seed=3)
        src, tgt = as_points(source), as_points(target)
        for cfg in (ICPConfig(), ICPConfig.paper(), ICPConfig(max_correspondence_distance=0.3)):
            r = icp_point_to_point(src, tgt, config=cfg)
            pose, iters, conv = icp_point_to_point_reference(src, tgt, config=cfg)
            assert r.iterations == iters and r.converged == conv
            np.testing.assert_allclose(r.pose, pose, atol=1e-9)


def test_paper_preset_stops_early_on_translation_only():
    step = (0.05, 0.0, math.radians(1.0))
    source, target = _pair(step, noise=0.0)
    paper = icp_point_to_point(source, target, config=ICPConfig.paper())
    proper = icp_point_to_point(source, target)
    # err = ||mu_Q - R mu_P|| drops below 1 cm after a few updates while a good part of the
    # rotation is still uncorrected; the rule says "converged" anyway.
    assert paper.converged and paper.reason == "converged"
    assert paper.iterations <= 4
    assert _err(paper.pose, step)[1] > 0.3
    assert proper.iterations > paper.iterations
    assert _err(proper.pose, step)[1] < 0.1
    # the last update of the paper preset was below 1 cm: one more paper iteration from its
    # estimate moves less than 1 cm
    again = icp_point_to_point(
        source, target, initial=paper.pose, config=ICPConfig(max_iterations=1, stop_rule="paper")
    )
    assert np.hypot(*(again.pose[:2] - paper.pose[:2])) < 0.05


def test_initial_guess_is_used():
    step = (0.3, 0.0, math.radians(10.0))
    source, target = _pair(step)
    r = icp_point_to_point(source, target, initial=step)
    assert r.converged and r.iterations < 8
    assert _err(r.pose, step)[0] < 0.005


def test_unconverged_case_reports_it():
    source, target = _pair((0.3, 0.0, math.radians(10.0)))
    r = icp_point_to_point(source, target, config=ICPConfig(max_iterations=2))
    assert not r.converged and r.reason == "max_iterations" and r.iterations == 2
    assert r.ok
    assert r.metrics()["converged"] == 0.0


def test_degeneracy_eigenvalue_corridor_vs_room():
    room_src, room_tgt = _pair((0.1, 0.0, 0.02))
    cor = corridor_segments()
    cor_src, cor_tgt = _pair((0.1, 0.0, 0.0), segments=cor, start=np.zeros(3))
    for icp in (icp_point_to_point, icp_point_to_line):
        room = icp(room_src, room_tgt)
        corr = icp(cor_src, cor_tgt)
        assert corr.eigenvalues[0] < 0.01 * room.eigenvalues[0]
        assert room.eigenvalues[0] > 50
        assert np.all(np.diff(room.eigenvalues) >= 0)
        # the weak direction of the corridor is x (along the walls)
        _w, v = np.linalg.eigh(corr.hessian)
        assert abs(v[0, 0]) > 0.99
        # across the corridor and in rotation it is still well constrained
        assert abs(corr.pose[1]) < 0.01 and abs(corr.pose[2]) < math.radians(0.2)


def test_metrics_are_flat_floats_with_known_values():
    step = (0.1, 0.05, 0.03)
    source, target = _pair(step, noise=0.0)
    r = icp_point_to_point(source, target)
    m = r.metrics()
    assert all(isinstance(v, float) for v in m.values())
    for k in (
        "iterations",
        "converged",
        "mean_residual",
        "median_residual",
        "inlier_ratio",
        "eig_min",
        "eig_max",
        "condition_number",
        "n_source",
        "n_target",
        "translation",
        "rotation",
    ):
        assert k in m
    assert m["translation"] == pytest.approx(math.hypot(0.1, 0.05), abs=5e-3)
    assert m["rotation"] == pytest.approx(0.03, abs=1e-3)
    assert m["condition_number"] == pytest.approx(m["eig_max"] / m["eig_min"])
    assert m["n_source"] == float(r.n_source)
    assert r.hessian.shape == (3, 3) and np.allclose(r.hessian, r.hessian.T)


def _scan_with(ranges):
    return make_scan(ROOM, P0).with_ranges(ranges)


@pytest.mark.parametrize("icp", [icp_point_to_point, icp_point_to_line])
def test_bad_inputs_never_crash(icp):
    good = make_scan(ROOM, P0)
    all_inf = _scan_with(np.full(RPLIDAR.n_beams, np.inf))
    few = np.full(RPLIDAR.n_beams, np.inf)
    few[:3] = 2.0
    cases = [
        (all_inf, good),
        (good, all_inf),
        (_scan_with(few), good),
        (np.zeros((0, 2)), good),
        (np.array([[np.nan, 1.0]] * 10), good),
    ]
    for src, tgt in cases:
        r = icp(src, tgt)
        assert isinstance(r, MatchResult)
        assert not r.converged and not r.ok and "too few" in r.reason
        assert math.isnan(r.mean_residual) and r.iterations == 0
        np.testing.assert_array_equal(r.pose, np.zeros(3))
    r = icp(good, good, initial=[np.nan, 0.0, 0.0])
    assert not r.converged and "initial" in r.reason
    # NaN rows are dropped, the rest still matches
    pts = as_points(good)
    noisy = np.vstack([pts, [[np.nan, np.nan], [np.inf, 0.0]]])
    r = icp(noisy, pts)
    assert r.converged and r.n_source == pts.shape[0]
    # identical scans: converged at once, zero motion
    r = icp(good, good)
    assert r.converged and r.iterations == 1 and np.abs(r.pose).max() < 1e-9
    # all points on one spot (no normals, no structure)
    blob = np.ones((50, 2))
    r = icp(blob, blob)
    assert isinstance(r, MatchResult)


def test_wrong_shapes_raise_matching_error():
    with pytest.raises(MatchingError, match="shape"):
        icp_point_to_point(np.zeros((10, 3)), np.zeros((10, 2)))
    with pytest.raises(MatchingError, match="initial"):
        icp_point_to_point(np.ones((10, 2)), np.ones((10, 2)), initial=[0.0, 1.0])


def test_max_correspondence_distance_limits_pairs():
    source, target = _pair((0.05, 0.0, 0.01))
    far = as_points(source) + 100.0
    r = icp_point_to_point(far, target, config=ICPConfig(max_correspondence_distance=0.5))
    assert not r.converged and "correspondences" in r.reason


def test_grid_nearest_neighbour_is_exact():
    rng = np.random.default_rng(7)
    tgt = as_points(make_scan(ROOM, P0))
    tree = cKDTree(tgt)
    queries = np.vstack(
        [
            tgt + rng.normal(0, 0.02, tgt.shape),
            rng.uniform(-40, 40, (300, 2)),  # far outside the grid
            rng.uniform(-6, 6, (300, 2)),
        ]
    )
    d_ref, i_ref = tree.query(queries)
    for cell in (0.05, 0.2, 1.0):
        start, order, spts, x0, y0, nx, ny = _grid.build_grid(tgt, cell)
        grid = (start, spts, x0, y0, cell, nx, ny)
        # a cover radius smaller and larger than the noise, the adaptive one, and no cover (a
        # target much larger than the source: the grid answers every query)
        structures = [
            (grid, _grid.build_cover(spts, rho)) for rho in (0.01, 0.05, _grid.cover_radius(tgt))
        ] + [(grid, _grid.no_cover())]
        for q, dr, ir in zip(queries, d_ref, i_ref, strict=True):
            j, d2 = _grid.nearest(q[0], q[1], start, spts, x0, y0, cell, nx, ny, np.inf)
            assert order[j] == ir and math.isclose(math.sqrt(d2), dr, abs_tol=1e-12)
            # the ICP's query (cover first, then hinted search) from an arbitrary (bad) hint
            for grid, cover in structures:
                hint = int(rng.integers(len(tgt)))
                jh, d2h = _grid.find_nearest(q[0], q[1], hint, -1, *grid, *cover, np.inf)
                assert order[jh] == ir and math.isclose(math.sqrt(d2h), dr, abs_tol=1e-12)
        # with a radius: nothing beyond it
        j, _ = _grid.nearest(50.0, 50.0, start, spts, x0, y0, cell, nx, ny, 1.0)
        assert j == -1


def test_cover_query_is_exact_on_sparse_and_far_flung_scans():
    # A 1-degree SICK-like scan (sparse: the adaptive cover radius exceeds its 5 cm floor)
    # plus a few points 150-200 m away that force coarse cover cells: the ICP's query must still
    # return cKDTree's neighbour everywhere.
    rng = np.random.default_rng(11)
    sick = SensorInfo(
        name="sick", n_beams=181, angle_min=-np.pi / 2, angle_increment=np.pi / 180,
        range_min=0.1, range_max=80.0, rate_hz=5.0,
    )  # fmt: skip
    tgt = as_points(make_scan(ROOM, P0, sensor=sick, noise=0.01, rng=rng))
    tgt = np.vstack([tgt, rng.uniform(150.0, 200.0, (5, 2))])
    cell = _grid.choose_cell_size(tgt, 0.15)
    start, order, spts, x0, y0, nx, ny = _grid.build_grid(tgt, cell)
    rho = _grid.cover_radius(tgt)
    assert rho > _grid.COVER_MIN_RADIUS  # the spacing rule, not the floor
    grid = (start, spts, x0, y0, cell, nx, ny)
    cover = _grid.build_cover(spts, rho)
    assert 1.0 / cover[6] > 2 * rho  # the 80 m returns made the cover's cells grow
    queries = np.vstack(
        [tgt + rng.normal(0, 0.03, tgt.shape), rng.uniform(-8, 8, (400, 2)), [[170.0, 170.0]]]
    )
    d_ref, i_ref = cKDTree(tgt).query(queries)
    for q, dr, ir in zip(queries, d_ref, i_ref, strict=True):
        j, d2 = _grid.find_nearest(q[0], q[1], -1, -1, *grid, *cover, np.inf)
        assert math.isclose(math.sqrt(d2), dr, abs_tol=1e-12)
        assert order[j] == ir or math.isclose(np.hypot(*(tgt[order[j]] - q)), dr, abs_tol=1e-12)


def test_registry():
    assert {"icp", "icp-paper", "plicp"} <= set(MATCHERS)
    m = get_matcher("icp-paper")
    assert isinstance(m, Matcher) and m.name == "icp-paper"
    source, target = _pair((0.05, 0.0, math.radians(1.0)), noise=0.0)
    r_paper = m(source, target)
    r_direct = icp_point_to_point(source, target, config=ICPConfig.paper())
    np.testing.assert_array_equal(r_paper.pose, r_direct.pose)
    r_pl = get_matcher("plicp")(source, target)
    assert r_pl.method == "icp_point_to_line"
    with pytest.raises(MatchingError, match=r"unknown matcher 'ndt'.*icp-paper"):
        get_matcher("ndt")
    custom = get_matcher("icp", ICPConfig(max_iterations=1))
    assert custom(source, target).iterations == 1

    class Fixed:
        name = "fixed-test"

        def __call__(self, source, target, initial=None):
            return icp_point_to_point(source, target, initial)

    register_matcher(Fixed())
    try:
        assert get_matcher("fixed-test")(source, target).converged
        with pytest.raises(MatchingError, match="already"):
            register_matcher(Fixed())
    finally:
        MATCHERS.pop("fixed-test")


def test_config_yaml_round_trip(tmp_path):
    cfg = ICPConfig.paper()
    p = cfg.save(tmp_path / "icp.yaml")
    assert ICPConfig.from_yaml(p) == cfg
    assert cfg.stop_rule == "paper" and cfg.translation_tol == 0.01 and cfg.max_iterations == 20


def test_transform_convention():
    # transform_points(estimate, current) lands on previous
    step = (0.2, -0.1, 0.05)
    source, target = _pair(step, noise=0.0)
    r = icp_point_to_line(source, target)
    moved = transform_points(r.pose, as_points(source))
    d, _ = cKDTree(as_points(target)).query(moved)
    assert np.median(d) < 0.01


@pytest.mark.parametrize("cell", [0.05, 0.1, 0.15])
def test_pending_block_normals_fill_to_the_eager_ones(cell):
    """Blocks computed when first read (a target much larger than its source) give every point
    the normal the whole cache gives, bit for bit, whichever point of a block comes first."""
    rng = np.random.default_rng(4)
    seg = room_segments()
    pts = np.vstack(
        [as_points(make_scan(seg, (0.3 * k, 0.1 * k, 0.05 * k))) for k in range(4)]
        + [rng.uniform(-6, 6, (40, 2))]  # sparse blocks: the disc instead
    )
    start, _order, spts, x0, y0, nx, ny = _grid.build_grid(pts, cell)
    eager = _grid.block_normals(start, spts, x0, y0, cell, nx, ny, 3)
    for order in (np.arange(len(spts)), rng.permutation(len(spts))):
        lazy = _grid.pending_block_normals(start, len(spts), nx * ny)
        for i in order[: len(order) // 2]:  # half the points: the others' blocks partly filled
            want = _grid.point_normal(i, start, spts, x0, y0, cell, nx, ny, 0.15, 3, eager)
            got = _grid.point_normal(i, start, spts, x0, y0, cell, nx, ny, 0.15, 3, lazy)
            assert np.array_equal(np.array(got), np.array(want), equal_nan=True)
        firsts = start[:-1][start[:-1] < start[1:]]  # the rows the cache keys blocks by
        assert (lazy[firsts, :, 2] == _grid.BLOCK_PENDING).any()  # blocks nobody read: never made


@pytest.mark.parametrize("cell", [0.05, 0.1, 0.5])
def test_target_normals_on_known_walls(cell):
    # scan from the origin of an axis-aligned room: points on the long walls have normals
    # along y, on the short walls along x (block PCA for small cells, disc PCA otherwise)
    seg = room_segments(pillars=False)
    pts = as_points(make_scan(seg, (0.0, 0.0, 0.0)))
    start, _order, spts, x0, y0, nx, ny = _grid.build_grid(pts, cell)
    normals, planarity = _grid.grid_normals(start, spts, x0, y0, cell, nx, ny, 0.15, 3)
    bottom = np.abs(spts[:, 1] + 3.0) < 1e-6
    bottom &= np.abs(spts[:, 0]) < 4.0  # away from corners
    left = np.abs(spts[:, 0] + 5.0) < 1e-6
    left &= np.abs(spts[:, 1]) < 2.5
    assert bottom.sum() > 100 and left.sum() > 50
    assert np.all(np.abs(normals[bottom, 1]) > 0.999)
    assert np.all(np.abs(normals[left, 0]) > 0.999)
    assert np.all(planarity[bottom] > 0.99)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 64, 65, 300])
def test_order_statistics_are_numpys_bit_for_bit(n: int) -> None:
    from scanguard.matching._grid import kth_smallest, median

    rng = np.random.default_rng(n)
    for values in (
        rng.random(n),
        np.round(rng.random(n) * 4) / 4,  # many ties
        np.full(n, 0.5),
        np.sort(rng.random(n))[::-1].copy(),
    ):
        assert median(values) == np.median(values)
        for k in {0, n // 2, n - 1}:
            a = values.copy()
            got = kth_smallest(a, k)
            assert got == np.partition(values, k)[k]
            # reordered around it, and still the same values
            assert (a[:k] <= got).all() and (a[k + 1 :] >= got).all()
            np.testing.assert_array_equal(np.sort(a), np.sort(values))
    assert np.isnan(median(np.zeros(0)))
