"""The wheel-support test: a person keeping pace ahead against wheels that spin in place."""

from __future__ import annotations

import numpy as np
import pytest

from scanguard.geometry import inverse, transform_points
from scanguard.slam.gate import Gate
from scanguard.slam.judge import Verdict
from scanguard.slam.wheel_support import SupportCount, WheelSupport

STEP = 0.1  # m the robot moves per scan, straight along +x


def _building() -> np.ndarray:
    """A plain corridor (walls at y = +-1) with a door post every 2 m: world points."""
    xs = np.arange(-5.0, 20.0, 0.05)
    walls = [np.column_stack([xs, np.full_like(xs, y)]) for y in (-1.0, 1.0)]
    posts = [
        np.column_stack([np.full(7, x), np.linspace(0.7, 1.0, 7) * side])
        for x in np.arange(1.0, 20.0, 2.0)
        for side in (-1.0, 1.0)
    ]
    return np.vstack(walls + posts)


def _person(at_x: float) -> np.ndarray:
    """A person's front, 0.8 m ahead of ``at_x``: an arc of 0.4 m."""
    a = np.linspace(-1.2, 1.2, 15)
    return np.column_stack([at_x + 0.8 - 0.2 * np.cos(a), 0.2 * np.sin(a)])


def _scan(robot_x: float, world: np.ndarray) -> np.ndarray:
    pts = transform_points(inverse(np.array([robot_x, 0.0, 0.0])), world)
    return pts[(np.hypot(*pts.T) < 8.0) & (pts[:, 0] > 0.0)]  # a 180-degree sensor


def _counts(truth_x, wheels_x, matches, person: bool) -> list[SupportCount | None]:
    ws = WheelSupport(np.zeros(3))
    out = []
    for i, (x, w) in enumerate(zip(truth_x, wheels_x, strict=True)):
        world = np.vstack([_building(), _person(x)]) if person else _building()
        m = None if i == 0 else np.array([matches[i - 1], 0.0, 0.0])
        out.append(ws.push(_scan(x, world), np.array([w, 0.0, 0.0]), m))
    return out


def test_a_person_keeping_pace_makes_the_building_support_the_wheels() -> None:
    truth = STEP * np.arange(12)
    # the matches follow the person: a fifth of the travel
    counts = _counts(truth, truth, [0.2 * STEP] * 11, person=True)
    assert counts[:5] == [None] * 5  # until the window holds five matches
    ws = WheelSupport(np.zeros(3))
    fired = [ws.fires(c) for c in counts[5:]]
    assert all(fired)
    assert all(c is not None and c.wheels >= 10 and c.matches > 0 for c in counts[5:])


def test_the_points_that_support_the_matches_are_the_person() -> None:
    truth = STEP * np.arange(12)
    # matches that follow the person whole: no motion at all
    counts = _counts(truth, truth, [0.0] * 11, person=True)
    assert all(WheelSupport(np.zeros(3)).fires(c) for c in counts[5:])
    n_person = len(_person(0.0))  # the scan lists the person's points last
    for c in counts[5:]:
        assert c is not None and c.follower is not None
        assert c.follower[-n_person:].all()  # the person, all of it
        # and little of the building: the far ends of the walls, beyond the old scan's range
        # where the wheels place them, 16 of 372 points
        assert c.follower[:-n_person].mean() <= 0.05


def test_wheels_that_spin_in_place_are_supported_by_nothing() -> None:
    still = np.zeros(12)
    wheels = STEP * np.arange(12)  # the wheels say it moved; the scans say it did not
    counts = _counts(still, wheels, [0.0] * 11, person=False)
    ws = WheelSupport(np.zeros(3))
    assert not any(ws.fires(c) for c in counts)
    assert all(c is not None and c.wheels == 0 and c.matches >= 20 for c in counts[5:])


def test_right_matches_and_right_wheels_support_neither() -> None:
    truth = STEP * np.arange(12)
    counts = _counts(truth, truth, [STEP] * 11, person=False)
    assert all(c == SupportCount(0, 0) for c in counts[5:])


def test_a_missing_match_or_odometry_restarts_the_window() -> None:
    ws = WheelSupport(np.zeros(3), window=2)
    pts = _scan(0.0, _building())
    m = np.array([STEP, 0.0, 0.0])
    assert ws.push(pts, np.zeros(3), None) is None
    assert ws.push(pts, np.array([STEP, 0.0, 0.0]), None) is None  # not matched
    assert ws.push(pts, np.array([2 * STEP, 0.0, 0.0]), m) is None  # window holds a gap
    assert ws.push(pts, np.array([3 * STEP, 0.0, 0.0]), m) is not None
    assert ws.push(pts, None, m) is None  # no odometry: forgotten
    assert ws.push(pts, np.zeros(3), m) is None


@pytest.mark.parametrize("kind", ["cnn", "both", "baseline", "none", "oracle"])
def test_the_gate_rejects_a_wheel_supported_pair_only_when_asked(kind) -> None:  # type: ignore[no-untyped-def]
    verdict = Verdict(fault_probability=0.01, baseline_score=0.01, wheel_supported=True)
    on = Gate(kind, cnn_threshold=0.5, baseline_threshold=0.5, wheel_support=True)
    off = Gate(kind, cnn_threshold=0.5, baseline_threshold=0.5)
    assert off.decide(verdict).accepted
    expect_reject = kind in ("cnn", "both")
    decision = on.decide(verdict)
    assert decision.accepted is not expect_reject
    if expect_reject:
        assert decision.reason == "rejected_wheels"
    # the back end drops a wheel-supported scan even where the CNN rejects it too
    faulty = Verdict(fault_probability=0.9, baseline_score=0.01, wheel_supported=True)
    if kind == "cnn":
        assert on.decide(faulty).reason == "rejected_wheels"
        assert off.decide(faulty).reason == "rejected_cnn"


def test_the_test_runs_by_default_with_the_graph_and_not_with_gmapping_or_the_paper() -> None:
    from pathlib import Path

    from scanguard.slam.config import RunConfig
    from scanguard.slam.guard import GuardConfig, policy_gate

    assert RunConfig().backend == "graph" and RunConfig().wheel_support()
    assert not RunConfig(backend="gmapping").wheel_support()
    assert RunConfig(backend="gmapping", guard={"wheel_support": True}).wheel_support()
    assert not RunConfig(guard={"wheel_support": False}).wheel_support()
    paper = Path(__file__).resolve().parents[1] / "configs" / "run_paper.yaml"
    assert not RunConfig.from_yaml(paper).wheel_support()
    # the streaming guard has no back end to ask: off unless asked
    assert not GuardConfig().wheel_support_on()
    gate = policy_gate(GuardConfig(policy="none"), None, None, wheel_support=True)
    assert (
        gate.wheel_support and not policy_gate(GuardConfig(policy="none"), None, None).wheel_support
    )
