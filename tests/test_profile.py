"""Per-beam residual profile: known residuals, segments in beam order, edge cases."""

from __future__ import annotations

import math

import numpy as np

from scanguard.pairs.profile import PROFILE_BINS, PROFILE_CLIP, residual_profile
from tests.helpers import make_scan, room_segments


def _room_points() -> np.ndarray:
    return make_scan(room_segments(), np.array([-1.0, -0.5, 0.1])).points(np.float64)


def test_perfect_alignment_is_the_floor_everywhere():
    pts = _room_points()
    prof = residual_profile(pts, pts, np.zeros(3))
    assert prof.shape == (PROFILE_BINS,)
    np.testing.assert_allclose(prof, math.log10(1e-3))


def test_a_wrong_match_lifts_every_segment_and_a_local_change_one():
    pts = _room_points()
    # a wrong estimate (0.28 m and 11 deg off) lifts almost every segment above 5 cm; a pure
    # slide along walls would not (point-to-point residuals stay at the point spacing there)
    wrong = residual_profile(pts, pts, np.array([0.2, 0.2, 0.2]))
    assert (wrong > math.log10(0.05)).mean() > 0.8
    # something moved in the first sixteenth of the beams only (in beam order)
    moved = pts.copy()
    k = len(pts) // PROFILE_BINS
    moved[:k] *= 0.8  # 20 % closer: a person in front of the wall
    local = residual_profile(pts, moved, np.zeros(3))
    assert local[0] > math.log10(0.05)
    np.testing.assert_allclose(local[2:], math.log10(1e-3))


def test_no_points_or_no_pose_is_far_everywhere():
    pts = _room_points()
    far = math.log10(PROFILE_CLIP)
    np.testing.assert_allclose(residual_profile(np.zeros((0, 2)), pts, np.zeros(3)), far)
    np.testing.assert_allclose(residual_profile(pts, pts, np.array([np.nan, 0, 0])), far)
    # fewer points than segments: empty segments repeat the scan's median
    few = residual_profile(pts, pts[:5] + np.array([0.01, 0.0]), np.zeros(3))
    assert np.isfinite(few).all() and few.shape == (PROFILE_BINS,)


def test_a_model_that_reads_the_profile_gets_it_from_the_match():
    from scanguard.detect.detector import FaultDetector
    from scanguard.detect.model import PROFILE_METRIC_FEATURES, ModelConfig, build_model
    from scanguard.matching import get_matcher
    from scanguard.pairs.profile import PROFILE_FEATURES

    cfg = ModelConfig(
        in_channels=2,
        input_size=32,
        widths=[4] * 5,
        dense=[4],
        metrics=list(PROFILE_METRIC_FEATURES),
        metric_hidden=0,
    )
    det = FaultDetector(build_model(cfg), {"kind": "occupancy", "size": 32}, 0.5)
    assert det.reads_profile and det.reads_odometry
    prev = make_scan(room_segments(), np.array([-1.0, -0.5, 0.1]))
    cur = make_scan(room_segments(), np.array([-0.9, -0.5, 0.12]))
    match = get_matcher("icp")(cur.points(np.float64), prev.points(np.float64), None)
    feats = det.match_features(prev, cur, match)
    expected = residual_profile(prev.points(np.float64), cur.points(np.float64), match.pose)
    got = np.array([feats[n][0] for n in PROFILE_FEATURES])
    np.testing.assert_allclose(got, expected)
    p = det.fault_probability(prev, cur, match.pose, match)
    assert 0.0 <= p <= 1.0
