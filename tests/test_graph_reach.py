"""`scanguard.slam.graph.loop_search.search_reach`: a loop search that reaches as far as the
trajectory's uncertainty."""

from __future__ import annotations

import math
from collections import defaultdict

import gtsam
import numpy as np
import pytest

from scanguard.geometry import relative
from scanguard.scan import LaserScan, SensorInfo
from scanguard.slam.graph import ClosureCandidate
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.consistency import closure_sigmas
from scanguard.slam.graph.loop_search import relative_covariance, search_reach
from scanguard.slam.graph.solver import PoseGraphSolver


def _chain(n: int, sigma_xy: float, closure: bool = False) -> PoseGraphSolver:
    """``n`` nodes 0.5 m apart along x, each step known to ``sigma_xy`` (m) and 0.01 rad."""
    solver = PoseGraphSolver(gtsam, defaultdict(float), window=10)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Diagonal.Sigmas([1e-6] * 3)))
    v.insert(0, gtsam.Pose2())
    solver.commit(g, v, 1)
    step = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_xy, sigma_xy, 0.01]))
    for k in range(1, n):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        g.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(0.5, 0.0, 0.0), step))
        v.insert(k, gtsam.Pose2(0.5 * k, 0.0, 0.0))
        solver.commit(g, v, k + 1)
    if closure:  # the last node seen again from the first, to 1 cm
        g = gtsam.NonlinearFactorGraph()
        tight = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.001]))
        g.add(gtsam.BetweenFactorPose2(0, n - 1, gtsam.Pose2(0.5 * (n - 1), 0.0, 0.0), tight))
        solver.commit(g, gtsam.Values(), n, refresh_all=True)
    return solver


def test_the_fixed_reach_without_sigmas():
    cfg = GraphConfig(loop_search_sigmas=0.0)
    reach = search_reach(_chain(50, 0.05), 49, cfg)
    assert reach.radius == cfg.loop_search_maximum_distance
    assert (reach.window_xy, reach.window_theta) == (
        cfg.loop_matcher.window_xy,
        cfg.loop_matcher.window_theta,
    )


def test_the_default_reach_follows_the_uncertainty_every_third_search():
    graph = GraphConfig()
    assert (graph.loop_search_sigmas, graph.loop_wide_every) == (3.0, 3)
    assert graph.loop_window == "relative"
    reach = search_reach(_chain(400, 0.05), 399, graph)
    assert reach.radius > graph.loop_search_maximum_distance


def test_the_reach_grows_with_the_drift_and_shrinks_after_a_closure():
    cfg = GraphConfig(loop_search_sigmas=3.0, loop_search_max_radius=20.0)
    short = search_reach(_chain(20, 0.05), 19, cfg)
    long_ = search_reach(_chain(400, 0.05), 399, cfg)
    assert short.radius == cfg.loop_search_maximum_distance  # little drift: the least reach
    # 399 steps of 0.05 m sideways and 0.01 rad of heading, 200 m out: the heading dominates
    assert cfg.loop_search_maximum_distance < long_.radius <= 20.0
    assert long_.window_xy == long_.radius and long_.window_theta > cfg.loop_matcher.window_theta
    closed = search_reach(_chain(400, 0.05, closure=True), 399, cfg)
    assert closed.radius == cfg.loop_search_maximum_distance


def test_the_reach_is_capped():
    cfg = GraphConfig(loop_search_sigmas=3.0, loop_search_max_radius=6.0)
    reach = search_reach(_chain(400, 0.2), 399, cfg)
    assert reach.radius == pytest.approx(6.0) and reach.window_xy == pytest.approx(6.0)
    assert reach.window_theta <= np.pi


def test_a_search_between_two_wide_ones_keeps_the_fixed_reach():
    cfg = GraphConfig(loop_search_sigmas=3.0)
    solver = _chain(400, 0.05)
    assert search_reach(solver, 399, cfg, wide=False).radius == cfg.loop_search_maximum_distance
    assert search_reach(solver, 399, cfg).radius > cfg.loop_search_maximum_distance


def _loose_chain(n: int, step: np.ndarray) -> PoseGraphSolver:
    """``n`` nodes 0.5 m apart along x, turning 0.1 rad a step, node 0 known to 2 m."""
    solver = PoseGraphSolver(gtsam, defaultdict(float), window=10)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Diagonal.Sigmas([2, 2, 0.3])))
    v.insert(0, gtsam.Pose2())
    solver.commit(g, v, 1)
    noise = gtsam.noiseModel.Gaussian.Covariance(step)
    pose = gtsam.Pose2()
    for k in range(1, n):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        inc = gtsam.Pose2(0.5, 0.0, 0.1)
        pose = pose.compose(inc)
        g.add(gtsam.BetweenFactorPose2(k - 1, k, inc, noise))
        v.insert(k, pose)
        solver.commit(g, v, k + 1)
    return solver


def test_the_relative_covariance_of_neighbours_is_their_edge_not_their_marginals():
    step = np.array([[0.01**2, 2e-5, 0.0], [2e-5, 0.02**2, 1e-5], [0.0, 1e-5, 0.005**2]])
    solver = _loose_chain(30, step)
    est = solver.est
    rel = relative(est[28], est[29])
    cov = relative_covariance(solver.isam, 28, 29, rel)
    assert cov is not None
    # one edge between them: the edge's own covariance, although each node is known to ~2 m
    np.testing.assert_allclose(cov, step, rtol=1e-6, atol=1e-12)
    assert float(np.asarray(solver.isam.marginalCovariance(29))[0, 0]) > 1.0
    # two edges: compounded (first order) in the newer node's frame
    a = gtsam.Pose2(0.5, 0.0, 0.1)
    h = a.inverse().AdjointMap()
    two = relative_covariance(solver.isam, 27, 29, relative(est[27], est[29]))
    assert two is not None
    np.testing.assert_allclose(two, h @ step @ h.T + step, rtol=1e-6, atol=1e-12)


def test_the_relative_window_searches_a_recent_place_narrowly():
    solver = _loose_chain(30, np.diag([0.01**2, 0.01**2, 0.002**2]))
    sensor = SensorInfo("tiny", 3, -0.1, 0.1, 0.1, 10.0, 10.0)
    scan = LaserScan.from_sensor(sensor, 0.0, np.full(3, 2.0))
    claim = relative(solver.est[24], solver.est[29]) + np.array([0.0, 5.0, 0.0])
    cand = ClosureCandidate(29, 24, 29, 24, claim, 0.9, 0.9, np.eye(3) * 1e-4, scan, scan)
    relative_cfg = GraphConfig(match_covariance_scale=1.0)  # the default window
    marginal = relative_cfg.model_copy(update={"loop_window": "marginal"})
    # node 29 is known to ~2 m against node 0, so a wide search from it reaches 6+ m; five
    # edges of 1 cm from node 24 do not: the relative window stays the fixed 3 m
    assert math.isfinite(closure_sigmas(cand, solver.est, solver.isam, marginal))
    assert closure_sigmas(cand, solver.est, solver.isam, relative_cfg) == math.inf


def test_a_failed_centre_steers_the_next_search_along_its_chain() -> None:
    from types import SimpleNamespace

    from scanguard.slam.graph.loop_search import FailureMemory, candidate_chains

    # nodes 0-29 along a 3 m corridor, 30-58 far away, node 59 back in the corridor at 0.5 m
    est = np.zeros((60, 3))
    est[:30, 0] = 0.1 * np.arange(30)
    est[30:59] = np.column_stack([np.full(29, 100.0), 100.0 + np.arange(29), np.zeros(29)])
    est[59] = [0.5, 0.0, 0.0]
    nodes = [SimpleNamespace(path=float(i), accepted=True) for i in range(60)]
    cfg = GraphConfig(loop_submap_nodes=6)
    assert candidate_chains(nodes, est, 59, cfg) == [5]  # type: ignore[arg-type]
    # its submap (nodes 0-11) failed: the chain's nearest other node
    assert candidate_chains(nodes, est, 59, cfg, avoid=[5]) == [12]  # type: ignore[arg-type]
    assert candidate_chains(nodes, est, 59, cfg, avoid=[5, 18]) == [25]  # type: ignore[arg-type]
    assert candidate_chains(nodes, est, 59, cfg, avoid=[5, 18, 29]) == []  # type: ignore[arg-type]

    memory = FailureMemory(2)
    memory.add(7, 3)
    assert memory.recent(3) == []  # not within the round that failed
    assert memory.recent(4) == [7] and memory.recent(5) == [7]
    assert memory.recent(6) == []  # forgotten after two rounds
    off = FailureMemory(0)
    off.add(7, 3)
    assert off.recent(4) == []
