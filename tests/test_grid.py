"""Occupancy grid, map_server export, pose fusion and trajectory metrics (known answers)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from scanguard.geometry import compose, inverse, relative
from scanguard.slam.grid import (
    PGM_FREE,
    PGM_OCCUPIED,
    PGM_UNKNOWN,
    GridConfig,
    OccupancyGrid,
    chain,
    fuse_increments,
    read_pgm,
    robot_to_sensor_increment,
    save_maps_figure,
    sensor_to_robot_increment,
)
from scanguard.slam.metrics import centroid_distance, trajectory_errors
from tests.helpers import make_scan, room_segments


def test_single_scan_marks_walls_free_space_and_unknown():
    # room 10 x 6 centred at the origin; the lower wall is y = -3, right wall x = 5 (y < 0.9)
    grid = OccupancyGrid()
    grid.insert(make_scan(room_segments(pillars=False), (0.0, 0.0, 0.0)), (0.0, 0.0, 0.0))
    p = grid.probability()

    def prob(x, y):
        c, r = grid.world_to_cell([[x, y]])[0]
        return p[r, c]

    for x, y in [(0.3, -3.0 + 1e-3), (5.0 + 1e-3, -1.0), (-5.0 + 1e-3, 2.0)]:
        assert prob(x, y) > 0.65  # occupied wall cells
    for x, y in [(0.0, -2.0), (3.0, 1.0), (-4.0, -2.5), (0.05, 0.05)]:
        # free along the beams: one free update per scan (Bresenham rays of 8-connected
        # cells may leave isolated holes far from the sensor, so look at the 3x3 patch)
        c, r = grid.world_to_cell([[x, y]])[0]
        patch = grid.logodds[r - 1 : r + 2, c - 1 : c + 2]
        assert np.median(patch) == pytest.approx(-0.4) and patch.max() <= 0.0
    for x, y in [(0.0, -3.5), (6.0, -2.0), (-5.5, 0.0)]:
        assert prob(x, y) == pytest.approx(0.5)  # behind walls: never seen
    # each cell is updated at most once per scan (no over-counting near the sensor)
    assert grid.logodds.min() == pytest.approx(-0.4)
    assert 1 - 1 / (1 + np.exp(-0.4)) == pytest.approx(prob(0.0, -2.0))
    assert grid.logodds.max() == pytest.approx(0.85)


def test_grid_grows_and_keeps_cells():
    scan = make_scan(room_segments(), (0.0, 0.0, 0.0))
    big = OccupancyGrid(origin=(-20.0, -20.0), shape=(800, 800))
    big.insert(scan, (0.0, 0.0, 0.0))
    small = OccupancyGrid(origin=(1.0, 1.0), shape=(10, 10))
    small.insert(scan, (0.0, 0.0, 0.0))
    # the small grid grew to hold the scan; its cells agree with the big one cell for cell
    assert small.shape[0] > 10 and small.origin[0] < -5.0
    shift = np.round((small.origin - big.origin) / big.resolution).astype(int)
    np.testing.assert_allclose((small.origin - big.origin) / big.resolution, shift, atol=1e-6)
    r, c = small.shape
    np.testing.assert_array_equal(
        small.logodds, big.logodds[shift[1] : shift[1] + r, shift[0] : shift[0] + c]
    )


def test_repeated_scans_saturate_at_clamp():
    cfg = GridConfig(l_max=2.0, l_min=-1.0)
    grid = OccupancyGrid(cfg)
    scan = make_scan(room_segments(), (0.5, 0.2, 0.3))
    for _ in range(10):
        grid.insert(scan, (0.5, 0.2, 0.3))
    assert grid.logodds.max() == pytest.approx(2.0)
    assert grid.logodds.min() == pytest.approx(-1.0)


def test_map_server_pair_round_trip(tmp_path):
    grid = OccupancyGrid(GridConfig(resolution=0.1))
    for _ in range(4):  # four free updates (-1.6) pass the 0.196 free threshold
        grid.insert(make_scan(room_segments(), (1.0, -0.5, 0.4)), (1.0, -0.5, 0.4))
    _pgm, yml = grid.save_map_server(tmp_path / "map")
    meta = yaml.safe_load(yml.read_text())
    assert meta["image"] == "map.pgm" and meta["resolution"] == pytest.approx(0.1)
    assert meta["negate"] == 0 and meta["occupied_thresh"] == 0.65
    assert meta["free_thresh"] == 0.196 and meta["mode"] == "trinary"
    img = read_pgm(tmp_path / meta["image"])
    assert img.shape == grid.shape
    assert set(np.unique(img).tolist()) == {PGM_OCCUPIED, PGM_UNKNOWN, PGM_FREE}
    # map_server semantics: p = (255 - v) / 255; row 0 is the top of the map
    occ = (255 - img.astype(float)) / 255 > meta["occupied_thresh"]
    free = (255 - img.astype(float)) / 255 < meta["free_thresh"]
    h = img.shape[0]
    ox, oy, _ = meta["origin"]

    def pixel_of(x, y):
        return h - 1 - int(np.floor((y - oy) / 0.1)), int(np.floor((x - ox) / 0.1))

    assert occ[pixel_of(0.3, -3.0 + 1e-3)]  # bottom wall
    assert free[pixel_of(1.0, -0.5)]  # the sensor position
    assert not occ[pixel_of(0.0, -3.5)] and not free[pixel_of(0.0, -3.5)]
    png = grid.save_png(tmp_path / "map.png")
    import matplotlib.image as mpimg

    assert mpimg.imread(png).shape[:2] == grid.shape
    fig = save_maps_figure({"a": grid, "b": grid}, tmp_path / "maps.png", {"a": np.zeros((2, 3))})
    assert fig.stat().st_size > 1000
    assert not list(tmp_path.glob(".*"))  # atomic writes leave no temporaries


def test_increment_frames_and_fusion():
    rng = np.random.default_rng(1)
    robot = chain((1.0, 2.0, 0.3), rng.normal(0, 0.2, (10, 3)))
    off = np.array([0.25, -0.1, 0.4])
    laser = compose(robot, off)
    sensor_inc = relative(laser[:-1], laser[1:])
    robot_inc = relative(robot[:-1], robot[1:])
    np.testing.assert_allclose(sensor_to_robot_increment(sensor_inc, off), robot_inc, atol=1e-12)
    np.testing.assert_allclose(robot_to_sensor_increment(robot_inc, off), sensor_inc, atol=1e-12)
    np.testing.assert_allclose(chain(robot[0], robot_inc), robot, atol=1e-12)
    fallback = np.zeros_like(robot_inc)
    acc = np.ones(10, bool)
    acc[[2, 5]] = False
    matched = robot_inc.copy()
    matched[5] = np.nan  # a failed match is never used, even if marked accepted
    acc_nan = acc.copy()
    acc_nan[5] = True
    fused = fuse_increments(robot[0], matched, fallback, acc_nan)
    np.testing.assert_allclose(fused[2], fused[3])  # step 2 -> 3 stood still
    np.testing.assert_allclose(fused[5], fused[6])
    np.testing.assert_allclose(relative(fused[3], fused[4]), robot_inc[3], atol=1e-12)
    with pytest.raises(ValueError, match="disagree"):
        fuse_increments(robot[0], matched, fallback, acc[:3])


def test_trajectory_errors_known_answers():
    stamps = np.arange(50) * 0.1
    ref = chain((0.0, 0.0, 0.0), np.tile([0.1, 0.0, 0.05], (49, 1)))
    exact = trajectory_errors(stamps, ref, ref)
    assert exact.ate_rmse < 1e-9 and exact.rpe_trans_rmse < 1e-9
    # one faulty step of 0.2 m sideways: RPE(delta=1) has exactly one 0.2 m error
    inc = relative(ref[:-1], ref[1:])
    inc[10, 1] += 0.2
    est = chain(ref[0], inc)
    e = trajectory_errors(stamps, est, ref, align=False)
    assert e.rpe_trans_rmse == pytest.approx(0.2 / np.sqrt(49), rel=1e-6)
    assert e.rpe_trans_mean == pytest.approx(0.2 / 49, rel=1e-6)
    assert e.rpe_rot_rmse_deg == pytest.approx(0.0, abs=1e-6)
    # unaligned ATE: rigidly shifted after step 11 -> known max
    assert e.ate_max > 0.2
    # an SE(2)-moved copy aligns away exactly
    moved = compose(np.array([3.0, -1.0, 0.7]), ref)
    assert trajectory_errors(stamps, moved, ref, align=True).ate_rmse < 1e-6
    assert trajectory_errors(stamps, moved, ref, align=False).ate_rmse > 1.0


def test_centroid_distance():
    prev = np.array([[1.0, 0.0], [3.0, 0.0], [2.0, 2.0]])
    pose = np.array([0.5, -0.2, 0.3])
    cur = (prev - pose[:2]) @ np.array(
        [[np.cos(pose[2]), -np.sin(pose[2])], [np.sin(pose[2]), np.cos(pose[2])]]
    )  # so that pose maps cur onto prev
    assert centroid_distance(prev, cur, pose) == pytest.approx(0.0, abs=1e-12)
    assert centroid_distance(prev, cur, compose(pose, [0.0, 0.3, 0.0])) == pytest.approx(0.3)
    assert np.isnan(centroid_distance(prev[:0], cur, pose))
    np.testing.assert_allclose(compose(pose, inverse(pose)), 0.0, atol=1e-12)
