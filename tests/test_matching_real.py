"""scanguard.matching on real scans: known motions, a static scanner, a peer cross-check."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from scanguard.geometry import inverse, transform_points
from scanguard.io import read_sequence
from scanguard.matching import ICPConfig, as_points, icp_point_to_line, icp_point_to_point

HERE = Path(__file__).resolve().parent
EXCERPTS = HERE / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
CCNY = SHARED / "rosbag" / "ccny_laser_scan_matcher_demo.bag"
LEGS = SHARED / "rosbag" / "leg_tracker_positive_1.bag"

MOTIONS = [
    (0.05, 0.0, math.radians(1.0)),
    (0.1, -0.05, math.radians(-3.0)),
    (0.3, 0.0, math.radians(5.0)),
    (0.0, 0.2, math.radians(-8.0)),
    (0.2, 0.1, math.radians(10.0)),
]


def _moved(points, motion, rng, noise=0.003, keep=0.9):
    """Source points seen after ``motion``: ``transform_points(motion, source)`` ~ target."""
    pts = points[rng.uniform(size=len(points)) < keep]
    pts = pts + rng.normal(0.0, noise, pts.shape)
    return transform_points(inverse(np.asarray(motion)), pts)


def _err(pose, truth):
    d = np.asarray(pose) - np.asarray(truth)
    return math.hypot(d[0], d[1]), abs(math.degrees((d[2] + math.pi) % (2 * math.pi) - math.pi))


@pytest.mark.parametrize(
    "excerpt", ["ccny-excerpt.bag", "intel-corrected-excerpt.log.gz"], ids=["ccny", "intel"]
)
@pytest.mark.parametrize("icp", [icp_point_to_point, icp_point_to_line], ids=["p2p", "pl"])
def test_recovers_known_motion_on_real_scans(excerpt, icp):
    seq = read_sequence(EXCERPTS / excerpt)
    rng = np.random.default_rng(11)
    errs = []
    for k, idx in enumerate((5, 25, 45)):
        target = as_points(seq[idx])
        for motion in MOTIONS:
            source = _moved(target, motion, rng)
            r = icp(source, target)
            dt, dth = _err(r.pose, motion)
            errs.append((dt, dth))
            assert dt < 0.01 and dth < 0.2, (excerpt, idx, motion, r.pose, r.iterations, k)
    assert len(errs) == 15


def test_real_scan_degeneracy_is_reported_per_sensor():
    # the same real scan, whole and cut down to one straight wall segment: the information
    # along the wall collapses
    seq = read_sequence(EXCERPTS / "ccny-excerpt.bag")
    pts = as_points(seq[10])
    r_full = icp_point_to_point(pts, pts)
    d = np.linalg.norm(pts - pts[len(pts) // 2], axis=1)
    wall = pts[d < 0.4]
    # keep only a locally straight run (PCA planarity)
    c = wall - wall.mean(axis=0)
    _w, v = np.linalg.eigh(c.T @ c)
    line = wall[np.abs(c @ v[:, 0]) < 0.02]
    assert len(line) > 100
    r_line = icp_point_to_point(line, line)
    assert r_line.eigenvalues[0] < 0.001 * r_full.eigenvalues[0]
    assert r_full.converged and r_full.eigenvalues[0] > 0


@pytest.mark.skipif(not LEGS.exists(), reason="shared data not available")
def test_static_scanner_with_walking_people_gives_zero_motion():
    seq = read_sequence(LEGS)
    for icp in (icp_point_to_point, icp_point_to_line):
        dts, dths = [], []
        for i in range(0, 120, 3):
            r = icp(seq[i + 1], seq[i])
            dt, dth = _err(r.pose, (0.0, 0.0, 0.0))
            dts.append(dt)
            dths.append(dth)
        assert np.median(dts) < 0.01 and np.median(dths) < 0.2, icp.__name__


@pytest.mark.skipif(not CCNY.exists(), reason="shared data not available")
def test_agrees_with_small_gicp_on_200_real_pairs():
    small_gicp = pytest.importorskip("small_gicp")
    seq = read_sequence(CCNY)
    cfg = ICPConfig()
    dts, dths = [], []
    for i in range(200):
        tgt = as_points(seq[i])
        src = as_points(seq[i + 1])
        ours = icp_point_to_point(src, tgt, config=cfg)
        z = np.zeros((len(src), 1))
        tc = small_gicp.PointCloud(np.hstack([tgt, np.zeros((len(tgt), 1))]))
        sc = small_gicp.PointCloud(np.hstack([src, z]))
        res = small_gicp.align(
            tc,
            sc,
            small_gicp.KdTree(tc),
            registration_type="ICP",
            max_correspondence_distance=1e3,  # exact nearest neighbour at any distance, as ours
            num_threads=1,
            max_iterations=cfg.max_iterations,
            rotation_epsilon=math.radians(cfg.rotation_tol_deg),
            translation_epsilon=cfg.translation_tol,
        )
        T = res.T_target_source
        peer = np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])
        dt, dth = _err(ours.pose, peer)
        dts.append(dt)
        dths.append(dth)
    assert np.median(dts) < 0.001 and np.median(dths) < 0.05
    # and they agree almost everywhere, not just in the median
    assert np.mean(np.asarray(dts) < 0.001) > 0.9
