"""ICPConfig.threads: the parallel nearest-neighbour search gives the single-thread answer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from scanguard.geometry import compose, inverse, transform_points
from scanguard.matching import ICPConfig, as_points, icp_point_to_line, icp_point_to_point
from tests.helpers import corridor_segments, make_scan, room_segments

EXCERPTS = Path(__file__).resolve().parent / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
CCNY_BAG = SHARED / "rosbag" / "ccny_laser_scan_matcher_demo.bag"

STEPS = [
    (0.05, 0.0, math.radians(1.0)),
    (0.05, 0.02, math.radians(4.0)),
    (0.3, 0.0, math.radians(10.0)),
    (-0.2, 0.15, math.radians(-7.0)),
]
CONFIGS = {
    "default": {},
    "paper": {"max_iterations": 20, "stop_rule": "paper", "translation_tol": 0.01},
    "max-dist": {"max_correspondence_distance": 0.1},
}


def _synthetic_pairs() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(3)
    start = np.array([0.3, 0.2, 0.1])
    out = []
    for segments in (room_segments(), corridor_segments()):
        for step in STEPS:
            target = as_points(make_scan(segments, start, noise=0.005, rng=rng))
            source = as_points(make_scan(segments, compose(start, step), noise=0.005, rng=rng))
            out.append((source, target, np.asarray(step)))
    return out


def _assert_same(r1, r2, tol=1e-9):
    d = np.abs(r1.pose - r2.pose)
    assert d[0] < tol and d[1] < tol and d[2] < tol, (r1.pose, r2.pose)
    assert r1.iterations == r2.iterations
    assert r1.converged == r2.converged
    assert r1.reason == r2.reason
    assert r1.n_inliers == r2.n_inliers
    assert r1.mean_residual == pytest.approx(r2.mean_residual, abs=1e-12)
    np.testing.assert_allclose(r1.hessian, r2.hessian, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("preset", list(CONFIGS))
@pytest.mark.parametrize("icp", [icp_point_to_point, icp_point_to_line], ids=["p2p", "pl"])
@pytest.mark.parametrize("threads", [2, 3])
def test_threads_give_single_thread_estimate_on_synthetic_pairs(icp, preset, threads):
    one = ICPConfig(**CONFIGS[preset])
    many = ICPConfig(**CONFIGS[preset], threads=threads)
    for source, target, _step in _synthetic_pairs():
        r1 = icp(source, target, None, one)
        r2 = icp(source, target, None, many)
        _assert_same(r1, r2)
    if preset == "default":
        # and the single-thread answer is the right one (room pairs: first half)
        for source, target, step in _synthetic_pairs()[: len(STEPS)]:
            r2 = icp(source, target, None, many)
            assert math.hypot(*(r2.pose[:2] - step[:2])) < 0.01
            assert abs(math.degrees(r2.pose[2] - step[2])) < 0.2


@pytest.mark.parametrize("icp", [icp_point_to_point, icp_point_to_line], ids=["p2p", "pl"])
def test_threads_are_deterministic_across_runs(icp):
    cfg = ICPConfig(threads=2)
    for source, target, _step in _synthetic_pairs()[:4]:
        runs = [icp(source, target, None, cfg) for _ in range(4)]
        for r in runs[1:]:
            assert np.array_equal(r.pose, runs[0].pose)
            assert r.iterations == runs[0].iterations
            assert r.mean_residual == runs[0].mean_residual
            assert np.array_equal(r.hessian, runs[0].hessian)


def test_threads_on_bad_input_flag_instead_of_crashing():
    cfg = ICPConfig(threads=2)
    pts = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [2.0, 0.5], [0.5, 2.0], [2.0, 2.0]])
    far = ICPConfig(threads=2, max_correspondence_distance=0.01)
    r = icp_point_to_point(pts + 5.0, pts, None, far)
    assert not r.converged and "too few correspondences" in r.reason
    r = icp_point_to_point(np.zeros((0, 2)), pts, None, cfg)
    assert not r.converged and "too few valid points" in r.reason
    # fewer source points than chunks: empty chunks are fine
    r = icp_point_to_point(pts, pts, None, ICPConfig(threads=16, min_points=3))
    assert r.converged and np.abs(r.pose).max() < 1e-12


def test_threads_must_be_positive():
    with pytest.raises(ValidationError):
        ICPConfig(threads=0)
    assert ICPConfig().threads == 1


def _real_pairs() -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    from scanguard.io import read_sequence

    rng = np.random.default_rng(5)
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
    for name in ("ccny-excerpt.bag", "intel-corrected-excerpt.log.gz"):
        seq = read_sequence(EXCERPTS / name)
        for idx in (5, 25, 45):
            target = as_points(seq[idx])
            # consecutive real pair (unknown motion) and a known motion of the same scan
            out.append((as_points(seq[idx + 1]), target, None))
            motion = np.array([0.2, -0.1, math.radians(6.0)])
            pts = target + rng.normal(0.0, 0.003, target.shape)
            out.append((transform_points(inverse(motion), pts), target, motion))
    return out


@pytest.mark.skipif(not (EXCERPTS / "ccny-excerpt.bag").exists(), reason="no real excerpts")
@pytest.mark.parametrize("icp", [icp_point_to_point, icp_point_to_line], ids=["p2p", "pl"])
def test_threads_give_single_thread_estimate_on_real_pairs(icp):
    for source, target, motion in _real_pairs():
        r1 = icp(source, target, None, ICPConfig())
        r2 = icp(source, target, None, ICPConfig(threads=2))
        _assert_same(r1, r2)
        if motion is not None:
            assert math.hypot(*(r2.pose[:2] - motion[:2])) < 0.01
            assert abs(math.degrees(r2.pose[2] - motion[2])) < 0.2


@pytest.mark.skipif(not CCNY_BAG.exists(), reason="shared data absent")
def test_threads_give_single_thread_estimate_on_consecutive_ccny_pairs():
    from scanguard.io import read_sequence

    seq = read_sequence(CCNY_BAG)
    for i in range(0, min(400, len(seq) - 1), 10):
        source, target = as_points(seq[i + 1]), as_points(seq[i])
        _assert_same(
            icp_point_to_point(source, target, None, ICPConfig()),
            icp_point_to_point(source, target, None, ICPConfig(threads=2)),
        )
