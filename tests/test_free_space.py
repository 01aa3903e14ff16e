"""Free space seen by recent scans: moving points left out of the matches (known answers)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.geometry import inverse, relative, transform_points
from scanguard.matching import get_matcher
from scanguard.slam.free_space import FreeSpaceHistory, RangeView
from scanguard.slam.guard import GuardConfig, ScanPairs
from scanguard.slam.judge import Verdict
from tests.helpers import PACE_STEP, box_segments, make_scan, pace_walk, room_segments

STEP = PACE_STEP


class _Normal:
    """A judge that calls every match normal."""

    def __call__(self, previous, current, match, odometry) -> Verdict:
        return Verdict(fault_probability=0.0)


def _translation_errors(free_space: FreeSpaceHistory | None) -> np.ndarray:
    scans, poses = pace_walk(30)
    pairs = ScanPairs(get_matcher("plicp"), _Normal(), free_space=free_space)
    errors = []
    for k, (scan, pose) in enumerate(zip(scans, poses, strict=True)):
        # the seed is the motion: what wheels (or the prediction) give the matcher
        pair = pairs.step(scan, guess=STEP if k else None)
        if k >= 10:  # once the history holds a second of views
            truth = relative(poses[k - 1], pose)
            errors.append(float(np.hypot(*(pair.match_increment[:2] - truth[:2]))))
    return np.asarray(errors)


def test_a_beam_that_reached_beyond_a_point_proves_it_gone() -> None:
    room = room_segments(width=10.0, height=6.0, pillars=False)
    scan = make_scan(room, (0.0, 0.0, 0.0))
    view = RangeView.of(scan)
    world = np.array([[2.0, 0.0], [5.0, 0.0], [4.9, 0.0], [0.0, 2.9]])
    gone = view.seen_through(np.zeros(3), world, 0.25)
    # 2 m out along a beam that hit the wall at 5 m: gone; on the wall, or just short of it,
    # within the margin: kept; beyond the wall (2.9 < 3, the wall) within the margin: kept
    assert gone.tolist() == [True, False, False, False]
    blind = RangeView(np.full_like(view.ranges, np.nan), view.angle_min, view.angle_increment)
    assert not blind.seen_through(np.zeros(3), world, 0.25).any()


def test_history_tests_points_only_against_views_old_enough() -> None:
    room = room_segments(width=10.0, height=6.0, pillars=False)
    history = FreeSpaceHistory(horizon=2.0, every=0.2, margin=0.25, min_age=0.5)
    for k in range(11):  # one second, a view every 0.2 s
        history.add(make_scan(room, (0.0, 0.0, 0.0), stamp=0.1 * k), np.zeros(3))
    points = np.array([[2.0, 0.0], [5.0, 0.0]])  # free space, the wall
    assert history.moving(points, np.zeros(3), 1.0).tolist() == [True, False]
    assert not history.moving(points, np.zeros(3), 0.3).any()  # no view 0.5 s old yet
    later = make_scan(room, (0.0, 0.0, 0.0), stamp=10.0)
    history.add(later, np.zeros(3))  # the old views leave the horizon
    assert not history.moving(points, np.zeros(3), 10.2).any()


def test_people_keeping_pace_no_longer_pull_the_match_short() -> None:
    without = _translation_errors(None)
    with_free_space = _translation_errors(GuardConfig(free_space_horizon=2.0).free_space_history())
    # people who keep pace look static to a scan-to-scan match: it stops short of the motion
    assert np.median(without) > 0.02
    assert np.median(with_free_space) < 0.005
    assert np.median(with_free_space) < 0.25 * np.median(without)


def test_on_with_the_graph_default_off_with_gmapping_and_the_paper() -> None:
    from pathlib import Path

    from scanguard.slam.config import RunConfig

    assert RunConfig().free_space_horizon() == 3.0  # the graph, the default back end
    assert RunConfig(backend="gmapping").free_space_horizon() == 0.0  # measured worse there
    assert GuardConfig().free_space_history() is None  # unset, and no auto given
    assert GuardConfig().free_space_history(3.0) is not None
    paper = RunConfig.from_yaml(Path(__file__).parents[1] / "configs" / "run_paper.yaml")
    assert paper.free_space_horizon() == 0.0
    assert GuardConfig(free_space_horizon=0.0).free_space_history() is None
    crowds = RunConfig.from_yaml(Path(__file__).parents[1] / "configs" / "run_crowds.yaml")
    assert crowds.graph.carve_frames == 4 and crowds.guard.free_space_lateral == 0.15
    assert RunConfig().graph.carve_frames == 0
    scans, _ = pace_walk(3)
    pairs = ScanPairs(get_matcher("plicp"), _Normal())
    for scan in scans:
        pair = pairs.step(scan, guess=STEP)
    assert pair.match is not None and math.isfinite(pair.match_increment[0])


def test_a_point_just_off_a_pillar_edge_is_not_a_person_with_a_lateral_window() -> None:
    room = np.vstack(
        [room_segments(width=14.0, height=10.0, pillars=False), np.array(box_segments(3.25, 0.0))]
    )
    view = RangeView.of(make_scan(room, (0.0, 0.0, 0.0)))
    # 2 cm beyond the pillar's edge (a pose error of centimetres), and a person in open space
    world = np.array([[3.0, 0.27], [2.0, 1.0]])
    assert view.seen_through(np.zeros(3), world, 0.25).tolist() == [True, True]
    assert view.seen_through(np.zeros(3), world, 0.25, lateral=0.15).tolist() == [False, True]


def _seen_through_numpy(view, pose, world, margin, lateral):
    """The array form the kernel replaced (session 12), kept as the reference."""
    local = transform_points(inverse(pose), world)
    rng = np.hypot(local[:, 0], local[:, 1])
    idx = np.rint((np.arctan2(local[:, 1], local[:, 0]) - view.angle_min) / view.angle_increment)
    n = len(view.ranges)
    half = np.ones(len(rng), dtype=np.int64)
    if lateral > 0.0:
        width = np.arctan2(lateral, np.maximum(rng, 1e-3)) / view.angle_increment
        half = np.clip(np.ceil(width), 1, 24).astype(np.int64)
    inside = (idx >= half) & (idx <= n - 1 - half)
    i = np.clip(idx, 0, n - 1).astype(np.int64)
    r = view.ranges
    nearest = r[i].copy()
    for d in range(1, int(half.max(initial=1)) + 1):
        lo, hi = r[np.maximum(i - d, 0)], r[np.minimum(i + d, n - 1)]
        nearest = np.where(half >= d, np.minimum(nearest, np.minimum(lo, hi)), nearest)
    return inside & (nearest > rng * 1.03 + margin)


@pytest.mark.parametrize("lateral", [0.0, 0.15, 0.4])
def test_the_kernel_answers_as_the_array_form(lateral: float) -> None:
    """Random views (with beams that prove nothing) and points: the same answer per point.

    (A point at the sensor itself has no bearing: there the two forms' last-bit differences in
    the local coordinates pick different beams.)
    """
    rng = np.random.default_rng(5)
    for trial in range(20):
        ranges = rng.uniform(6.0, 12.0) + rng.normal(0.0, 0.3, 361)  # walls
        ranges[rng.random(361) < 0.05] = rng.uniform(0.3, 3.0)  # people in front of them
        ranges[rng.random(361) < 0.02] = np.nan
        view = RangeView(ranges, -np.pi / 2, np.pi / 360)
        pose = np.array([*rng.normal(0, 2, 2), rng.uniform(-np.pi, np.pi)])
        world = rng.uniform(-14, 14, (2000, 2))
        got = view.seen_through(pose, world, 0.25, lateral)
        want = _seen_through_numpy(view, pose, world, 0.25, lateral)
        assert got.dtype == np.bool_ and got.shape == (2000,)
        np.testing.assert_array_equal(got, want, err_msg=f"trial {trial}")
        assert 0 < got.sum() < len(got)
