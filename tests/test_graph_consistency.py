"""The graph's consistency gate and final-check residual (`scanguard.slam.graph.consistency`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.scan import LaserScan, SensorInfo
from scanguard.slam.graph import ClosureCandidate, GraphConfig
from scanguard.slam.graph.consistency import (
    closure_sigmas,
    final_residual_sigmas,
    search_reach_limits,
)

SENSOR = SensorInfo(
    name="tiny",
    n_beams=3,
    angle_min=-0.1,
    angle_increment=0.1,
    range_min=0.1,
    range_max=10.0,
    rate_hz=10.0,
)


def _candidate(pose: tuple[float, float, float], cov: np.ndarray) -> ClosureCandidate:
    scan = LaserScan.from_sensor(SENSOR, 0.0, np.full(3, 2.0))
    return ClosureCandidate(
        node=1,
        target_node=0,
        scan_index=1,
        target_scan_index=0,
        pose=np.asarray(pose, dtype=np.float64),
        score=0.9,
        coarse_score=0.9,
        covariance=cov,
        source=scan,
        target=scan,
    )


class _Isam:
    """iSAM2's marginals, known: 0.1 m and 0.01 rad on node 1, exact node 0."""

    def marginalCovariance(self, key: int) -> np.ndarray:  # noqa: N802 (gtsam's name)
        return np.diag([0.1**2, 0.05**2, 0.01**2]) if key == 1 else np.zeros((3, 3))


class _WideIsam:
    """Node 1 uncertain to 2 m and 0.2 rad (a long drift), node 0 exact."""

    def marginalCovariance(self, key: int) -> np.ndarray:  # noqa: N802 (gtsam's name)
        return np.diag([2.0**2, 1.0**2, 0.2**2]) if key == 1 else np.zeros((3, 3))


def test_search_reach_limits_known_answers() -> None:
    fixed = GraphConfig(loop_search_sigmas=0.0)
    xy, theta = search_reach_limits(fixed)
    assert xy == pytest.approx(3.0 + 0.15 + 0.25) and theta == pytest.approx(0.5 + 0.1 + 0.1)
    # the reach follows the uncertainty (the default, 3 sigmas): without a marginal, the widest
    xy, theta = search_reach_limits(GraphConfig())
    assert xy == pytest.approx(25.0 + 0.15 + 0.25) and theta == pytest.approx(math.pi)
    # with the node's marginal: the wide search's own window, 3 x 2 m and 3 x 0.2 rad
    cov = _WideIsam().marginalCovariance(1)
    xy, theta = search_reach_limits(GraphConfig(), cov)
    assert xy == pytest.approx(6.0 + 0.4) and theta == pytest.approx(0.6 + 0.2)
    # a small marginal never narrows it below the fixed window
    xy, theta = search_reach_limits(GraphConfig(), np.diag([1e-4, 1e-4, 1e-6]))
    assert xy == pytest.approx(3.4) and theta == pytest.approx(0.7)
    assert search_reach_limits(fixed, cov) == search_reach_limits(fixed)


def test_the_gate_window_is_the_reach_a_search_from_the_node_has_now() -> None:
    # the newer node's marginal sets the window (`loop_window: marginal`; the relative
    # window, the default, is tested on a real iSAM2 chain in test_graph_reach.py)
    cfg = GraphConfig(match_covariance_scale=1.0, loop_window="marginal")
    est = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    cov = np.zeros((3, 3))
    # 5 m off across: beyond the fixed window, within the 6.4 m a search from node 1 reaches
    claim = _candidate((2.0, 5.0, 0.0), cov)
    assert math.isfinite(closure_sigmas(claim, est, _WideIsam(), cfg))
    assert (
        closure_sigmas(claim, est, _WideIsam(), cfg.model_copy(update={"loop_search_sigmas": 0.0}))
        == math.inf
    )
    # 10 m off: within the widest reach (25 m), not within this node's: refused
    assert closure_sigmas(_candidate((2.0, 10.0, 0.0), cov), est, _WideIsam(), cfg) == math.inf
    # with the known marginal of node 1 (0.1 m) the window stays the fixed one
    assert closure_sigmas(_candidate((2.0, 5.0, 0.0), cov), est, _Isam(), cfg) == math.inf


def test_closure_sigmas_known_answers() -> None:
    cfg = GraphConfig(match_covariance_scale=1.0, loop_window="marginal")
    est = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    cov = np.diag([0.0, 0.0, 0.0])
    assert closure_sigmas(_candidate((2.0, 0.0, 0.0), cov), est, _Isam(), cfg) == 0.0
    # 0.3 m off: sqrt(0.1^2 + 2^2 * 0.01^2) = 0.1020 m of translation sigma
    d = closure_sigmas(_candidate((2.3, 0.0, 0.0), cov), est, _Isam(), cfg)
    assert d == pytest.approx(0.3 / math.sqrt(0.01 + 4 * 1e-4))
    # 0.05 rad off: 5 sigmas of heading
    d = closure_sigmas(_candidate((2.0, 0.0, 0.05), cov), est, _Isam(), cfg)
    assert d == pytest.approx(5.0)
    # beyond the search's square window on one axis, not on the diagonal's length alone
    assert closure_sigmas(_candidate((2.0, 3.5, 0.0), cov), est, _Isam(), cfg) == math.inf
    assert math.isfinite(closure_sigmas(_candidate((5.3, 3.3, 0.0), cov), est, _Isam(), cfg))


def test_final_residual_sigmas_known_answers() -> None:
    est = np.array([[1.0, 1.0, 0.5], [1.0, 1.0, 0.5]])
    cov = np.diag([0.1**2, 0.1**2, 0.01**2])
    assert final_residual_sigmas(_candidate((0.0, 0.0, 0.0), cov), est) == pytest.approx(0.0)
    assert final_residual_sigmas(_candidate((0.2, 0.0, 0.0), cov), est) == pytest.approx(2.0)
