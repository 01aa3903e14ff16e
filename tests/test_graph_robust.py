"""Robust loop closures of the ``graph`` back end: one wrong closure must not fold the map.

Known answer: a square loop driven with exact odometry, whose node poses are known, closed by
its true closure; then one wrong closure (two corners 5.7 m apart claimed to be 0.5 m apart,
with a real closure's covariance) enters through `GraphBackend.add_closure`, the path real
closures take after the judge. The odometry factors are made as stiff as scan matches are on
a real log (centimetres), so the only question is how much the wrong factor may pull.
"""

from __future__ import annotations

import math

import numpy as np

from scanguard.geometry import relative, wrap_angle
from scanguard.scan import LaserScan, SensorInfo
from scanguard.slam.graph import ClosureCandidate, GraphBackend, GraphConfig
from scanguard.slam.graph.closure import ClosureRecord, ClosureVerdict

SENSOR = SensorInfo(
    name="tiny",
    n_beams=19,
    angle_min=-np.pi / 2,
    angle_increment=np.pi / 18,
    range_min=0.1,
    range_max=10.0,
    rate_hz=10.0,
)
SIDE = 4.0
STEP = 0.25
#: Largest node position error (m) the robust kernel leaves after the wrong closure.
TOLERANCE = 0.05
#: The same without a kernel is at least this (m): the map folds.
FOLDED = 0.5


def square_path() -> np.ndarray:
    """A lap of a 4 m square (0.25 m steps, two 45 deg turns in place at each corner)."""
    poses = [(0.0, 0.0, 0.0)]
    corners = [(SIDE, 0.0), (SIDE, SIDE), (0.0, SIDE), (0.0, 0.0)]
    x, y, h = poses[0]
    for cx, cy in corners:
        n = round(math.hypot(cx - x, cy - y) / STEP)
        for k in range(1, n + 1):
            poses.append((x + (cx - x) * k / n, y + (cy - y) * k / n, h))
        x, y = cx, cy
        for _ in range(2):
            h += math.pi / 4
            poses.append((x, y, h))
    return np.array(poses)


def _closure(b: GraphBackend, target: int, node: int, pose: np.ndarray) -> ClosureRecord:
    scan = b._nodes[node].scan
    cand = ClosureCandidate(
        node=node,
        target_node=target,
        scan_index=node,
        target_scan_index=target,
        pose=np.asarray(pose, dtype=np.float64),
        score=0.9,
        coarse_score=0.9,
        covariance=np.diag([1e-4, 1e-4, 1e-5]),  # a real closure's: 1 cm, 0.2 deg
        source=scan,
        target=b._nodes[target].scan,
    )
    return ClosureRecord(cand, ClosureVerdict(True, 0.9, "test"))


def _square_with_wrong_closure(kernel: str) -> tuple[np.ndarray, np.ndarray]:
    """Optimised node poses and the truth, after the true and one wrong closure."""
    truth = square_path()
    cfg = GraphConfig(
        loop_closure=False,
        closure_gate_sigmas=0,  # the kernel alone: the gate would refuse the wrong closure
        robust_kernel=kernel,  # type: ignore[arg-type]
        odom_sigma_xy=0.01,
        odom_sigma_theta=0.01,
        odom_sigma_theta_per_m=0.0,
        odom_floor_xy=0.005,
        odom_floor_theta=0.002,
    )
    b = GraphBackend(cfg, range_max=SENSOR.range_max)
    ranges = np.full(SENSOR.n_beams, 3.0)
    for i, pose in enumerate(truth):
        # usable=False: odometry factors only, no scan matching (the scans do not matter)
        b.update(LaserScan.from_sensor(SENSOR, 0.1 * i, ranges), pose, usable=False)
    assert b.stats["nodes"] == len(truth)
    last = len(truth) - 1
    assert b.add_closure(_closure(b, 0, last, relative(truth[0], truth[last])))
    corner_a = int(np.argmin(np.hypot(truth[:, 0] - SIDE, truth[:, 1])))  # (4, 0)
    corner_b = int(np.argmin(np.hypot(truth[:, 0], truth[:, 1] - SIDE)))  # (0, 4)
    assert math.dist(truth[corner_a, :2], truth[corner_b, :2]) > 5.0
    assert b.add_closure(_closure(b, corner_a, corner_b, np.array([0.5, 0.2, 0.1])))
    return b.node_poses(), truth


def _max_error(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    d = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    a = np.abs(wrap_angle(est[:, 2] - truth[:, 2]))
    return float(d.max()), float(a.max())


def test_cauchy_keeps_the_square_despite_a_wrong_closure() -> None:
    est, truth = _square_with_wrong_closure("cauchy")
    dxy, dth = _max_error(est, truth)
    assert dxy < TOLERANCE  # measured 0.15 mm
    assert dth < math.radians(0.5)


def test_huber_gives_way_part_of_the_distance() -> None:
    # Huber's cost grows linearly: the wrong closure keeps a constant pull however far it
    # is (measured 0.19 m), where Cauchy's pull fades with the residual
    est, truth = _square_with_wrong_closure("huber")
    dxy, _ = _max_error(est, truth)
    assert TOLERANCE < dxy < FOLDED


def test_without_a_kernel_the_wrong_closure_folds_the_square() -> None:
    est, truth = _square_with_wrong_closure("none")
    dxy, _ = _max_error(est, truth)
    assert dxy > FOLDED  # measured 5.1 m


def test_add_closure_records_the_closure_like_a_judged_one() -> None:
    b = GraphBackend(
        GraphConfig(loop_closure=False, closure_gate_sigmas=0), range_max=SENSOR.range_max
    )
    ranges = np.full(SENSOR.n_beams, 3.0)
    for i, pose in enumerate(square_path()[:30]):
        b.update(LaserScan.from_sensor(SENSOR, 0.1 * i, ranges), pose, usable=False)
    rec = _closure(b, 0, 29, np.array([0.1, 0.0, 0.0]))
    assert b.add_closure(rec)
    assert len(b.closures) == 1 and b.closures[0] is rec and rec.added
    assert b.edges[-1] == (0, 29, "loop")
    assert b.stats["closures_accepted"] == 1 and b.stats["closure_candidates"] == 0


def test_the_gate_refuses_a_claim_the_graph_cannot_explain_and_keeps_the_true_closure() -> None:
    truth = square_path()
    cfg = GraphConfig(
        loop_closure=False,
        odom_sigma_xy=0.01,
        odom_sigma_theta=0.01,
        odom_sigma_theta_per_m=0.0,
        odom_floor_xy=0.005,
        odom_floor_theta=0.002,
    )
    assert cfg.closure_gate_sigmas == 10.0  # the default
    b = GraphBackend(cfg, range_max=SENSOR.range_max)
    ranges = np.full(SENSOR.n_beams, 3.0)
    odom = truth.copy()
    odom[:, 0] += 0.003 * np.arange(len(odom))  # drifting: 0.22 m off by the end of the lap
    for i, pose in enumerate(odom):
        b.update(LaserScan.from_sensor(SENSOR, 0.1 * i, ranges), pose, usable=False)
    last = len(truth) - 1
    true = _closure(b, 0, last, relative(truth[0], truth[last]))
    assert b.add_closure(true) and true.added
    # 22 of the closure's own sigmas off, but within what the graph knows of its drift
    assert 0.5 < true.gate_sigmas < cfg.closure_gate_sigmas
    before = b.node_poses(optimized=False)
    corner_a = int(np.argmin(np.hypot(truth[:, 0] - SIDE, truth[:, 1])))  # (4, 0)
    corner_b = int(np.argmin(np.hypot(truth[:, 0], truth[:, 1] - SIDE)))  # (0, 4), 5.7 m away
    wrong = _closure(b, corner_a, corner_b, np.array([0.5, 0.2, 0.1]))
    assert not b.add_closure(wrong) and not wrong.added and wrong.inconsistent
    assert not true.inconsistent and true.as_dict()["gate_sigmas"] == true.gate_sigmas
    assert wrong.gate_sigmas == math.inf  # beyond any loop search's window
    # within the window, but 1.5 m off over 2 m of stiff path: many sigmas off
    near = _closure(b, corner_a - 8, corner_a, np.array([0.5, 0.0, 0.0]))
    assert not b.add_closure(near) and near.inconsistent
    assert 3 * cfg.closure_gate_sigmas < near.gate_sigmas < math.inf
    assert b.stats["closures_inconsistent"] == 2 and b.stats["closures_accepted"] == 1
    assert b.closures == [true, wrong, near] and b.edges[-1] == (0, last, "loop")
    np.testing.assert_array_equal(b.node_poses(optimized=False), before)  # nothing moved
