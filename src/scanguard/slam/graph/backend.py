"""`GraphBackend`: pose-graph SLAM with scan-to-local-map matching and judged loop closures.

The structure of Karto / slam_toolbox, with gtsam's iSAM2 as the solver:

1. **Nodes.** A scan becomes a node after ``minimum_travel_distance`` /
   ``minimum_travel_heading`` (or ``minimum_time_interval``) of odometry since the last node.
   Scans in between take the last node's pose composed with the odometry since it, as in
   GMapping's reported trajectory. Graph variables are *sensor* poses, so matches need no
   laser-offset conversion; the trajectory is converted back to robot poses.
2. **Odometry factor** between consecutive nodes, with noise growing with the distance and the
   rotation travelled.
3. **Scan-to-local-map factor.** When the guard accepted the scan (``usable``), it is matched
   by the correlative matcher (`scanguard.matching.correlative`) against a likelihood grid of
   the last ``local_map_nodes`` accepted scans at their current estimates, seeded by
   odometry, refined by point-to-line ICP; the factor's covariance is the matcher's
   response-surface covariance. A rejected scan gets the odometry factor only and is never
   put into any map (the paper's rule).
4. **Loop closures.** Every ``loop_search_every`` accepted nodes, older nodes within
   ``loop_search_maximum_distance`` of the current estimate (and at least ``loop_min_travel``
   back along the path) are grouped into chains of consecutive nodes; each chain's centre gets
   a submap (its neighbours' scans in its own frame, cached), searched by a wide coarse
   correlative match and refined by a fine one. The candidate goes to the `ClosureJudge`
   and, accepted, to the consistency gate (`scanguard.slam.graph.consistency`) before it
   may enter the graph, as a robust (Cauchy by default) between-factor.
5. **Optimisation.** iSAM2 after every node; a batch Levenberg-Marquardt pass when the
   trajectory is read (``batch_at_end``); optionally the final check drops closures the
   optimised graph contradicts and optimises again.

This module adds the nodes and factors; the parts live beside it: the local-map matching in
`scanguard.slam.graph.local_map`, the loop-closure search in `scanguard.slam.graph.loop_search`,
how a closure enters (judge, queues, gate, factor) in `scanguard.slam.graph.intake` and the
iSAM2 solver in `scanguard.slam.graph.solver`.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.geometry import as_pose, compose, inverse, relative, wrap_angle
from scanguard.scan import LaserScan
from scanguard.slam.backend import checked_odometry, finite_odometry
from scanguard.slam.graph.agreement import ClosureAgreement, ClosureConfirmation, FarAgreement
from scanguard.slam.graph.closure import AcceptAll, ClosureJudge, ClosureRecord
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.finished import FinishedGraph
from scanguard.slam.graph.intake import EDGE_MATCH, EDGE_ODOMETRY, ClosureIntake
from scanguard.slam.graph.local_map import GraphNode, NodeShape, local_map_points, match_local
from scanguard.slam.graph.loop_search import FailureMemory, NodeIndex, SubmapCache, loop_candidates
from scanguard.slam.graph.odometry import StepCovariance
from scanguard.slam.graph.solver import PoseGraphSolver, rotate_cov
from scanguard.slam.rows import Rows

logger = logging.getLogger(__name__)


#: The back end's counters (`GraphBackend.stats`), and its timers (s).
_COUNTERS = (
    "nodes",
    "matches_added",
    "matches_weak",
    "local_map_seeds",
    "matches_degenerate",
    "moving_points_left_out",
    "nodes_with_moving_points",
    "matches_refused",
    "closures_refused",
    "solver_refusals",
    "scans_rejected_by_guard",
    "loop_searches",
    "closure_candidates",
    "closures_accepted",
    "closures_rejected",
    "closures_dropped_final",
    "closures_inconsistent",
    "closures_agreed",
    "closures_waited",
    "closures_far",
    "closures_withdrawn",
)
_TIMERS = ("time_match_s", "time_isam_s", "time_loop_s", "time_judge_s", "time_batch_s")


class GraphBackend(ClosureIntake):
    """Pose-graph SLAM back end (``graph``); see the module docstring.

    Args:
        config: Parameters (defaults if None).
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose of the first scan.
        range_max: Sensor maximum range (m); beams at or beyond it are not points.
        closure_judge: Decides on loop-closure candidates (default: accept all).
        reference: Reference robot poses, one per scan that will be given (only to label
            closure candidates in `closures`; never used for estimation).
    """

    def __init__(
        self,
        config: GraphConfig | None = None,
        *,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
        initial_pose: ArrayLike = (0.0, 0.0, 0.0),
        range_max: float | None = None,
        closure_judge: ClosureJudge | None = None,
        reference: ArrayLike | None = None,
    ) -> None:
        import gtsam

        self._gtsam = gtsam
        self.config = config or GraphConfig()
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self.initial_pose = as_pose(initial_pose).reshape(3).copy()
        self.range_max = range_max
        self.closure_judge: ClosureJudge = closure_judge or AcceptAll()
        self._reference_sensor = (
            None
            if reference is None
            else compose(as_pose(reference).reshape(-1, 3), self.laser_offset)
        )
        self.labels = self.config.closures.labels
        self._loop_factor_index: dict[int, int] = {}  # closure record -> index in solver.graph
        self._nodes: list[GraphNode] = []
        # per scan given, for the whole recording: numpy buffers, not lists of small objects
        self._scan_node = Rows(np.int64)  # node each scan's pose hangs from
        self._scan_odom = Rows(np.float64, (3,))
        self._used = Rows(np.bool_)
        # accepted nodes that may be in the next local map, oldest first: they hold their
        # points and outline; older and rejected nodes derive them when (rarely) read
        self._held: deque[int] = deque()
        self._shape = NodeShape(
            self.config.max_range or range_max,
            min(self.config.sequential.resolution, self.config.loop_fine.resolution),
            self.config.carve_frames > 0,
        )
        self._last_node_stamp = -math.inf
        self._odo: NDArray[np.float64] | None = None
        self._steps = StepCovariance(self.laser_offset)  # since the last node
        self._next_cov: NDArray[np.float64] | None = None
        self._nonfinite_odometry = 0
        self._since_search = self.config.loop_search_phase % self.config.loop_search_every
        self._failures = FailureMemory(self.config.loop_fail_memory)
        self._cooldown = 0
        self._weak = 0  # consecutive weak sequential matches
        self._submaps = SubmapCache()
        self._agreement = ClosureAgreement(self.config, self.labels)
        self._confirmation = ClosureConfirmation(self.config, self.labels)
        self._far = FarAgreement(self.config, self.labels)
        self._node_index = NodeIndex()
        self._batch: NDArray[np.float64] | None = None
        self.edges: list[tuple[int, int, str]] = []
        self.closures: list[ClosureRecord] = []
        self.stats: dict[str, float] = dict.fromkeys(_COUNTERS, 0) | dict.fromkeys(_TIMERS, 0.0)
        self._solver = PoseGraphSolver(
            gtsam,
            self.stats,
            self.config.local_map_nodes,
            partial_relinearization=self.config.partial_relinearization,
        )

    @property
    def _est(self) -> NDArray[np.float64]:
        """Current estimates of the node sensor poses ``(M, 3)``."""
        return self._solver.est

    # ------------------------------------------------------------------ protocol
    @property
    def name(self) -> str:
        """``graph``."""
        return "graph"

    def _would_trigger(self, stamp: float, odom: NDArray[np.float64] | None) -> bool:
        if not self._nodes:
            return True
        cfg = self.config
        if cfg.minimum_time_interval >= 0 and stamp - self._last_node_stamp >= (
            cfg.minimum_time_interval
        ):
            return True
        if odom is None:
            return False
        inc = relative(self._nodes[-1].odom, odom)
        return bool(
            math.hypot(inc[0], inc[1]) >= cfg.minimum_travel_distance
            or abs(float(wrap_angle(inc[2]))) >= cfg.minimum_travel_heading
        )

    def wants_scan(self, stamp: float, odometry: NDArray[np.float64] | None) -> bool:
        """Whether `update` would make this scan a node (the loop judges only those)."""
        return self._would_trigger(stamp, finite_odometry(odometry))

    def update(
        self,
        scan: LaserScan,
        odometry: NDArray[np.float64] | None,
        *,
        usable: bool = True,
        match: NDArray[np.float64] | None = None,
    ) -> None:
        """Feed the next scan (``match``, the guard's scan-to-scan match, is not used).

        Args:
            scan: The new scan.
            odometry: Robot odometry pose at ``scan.stamp`` (absolute), or None (zero motion).
            usable: False when the guard rejected the scan: odometry factor only, no map.
            match: Unused: the graph matches each node against its own local map.
        """
        index = len(self._scan_node)
        prev = self._odo
        odom, self._nonfinite_odometry = checked_odometry(
            odometry, self._odo, index, self._nonfinite_odometry
        )
        self._odo = odom.copy()
        if prev is not None:
            self._steps.add(relative(prev, odom), self._next_cov)
        self._next_cov = None
        trigger = self._would_trigger(float(scan.stamp), odom)
        self._scan_odom.append(odom)
        if not trigger:
            self._scan_node.append(len(self._nodes) - 1)
            self._used.append(False)
            return
        self._batch = None
        accepted = self._add_node(index, scan, odom, usable=bool(usable))
        self._steps.reset()
        self._scan_node.append(len(self._nodes) - 1)
        self._used.append(accepted)

    @property
    def pose(self) -> NDArray[np.float64]:
        """Current robot pose (latest node composed with the odometry since)."""
        if not len(self._scan_node):
            return self.initial_pose.copy()
        return self._robot_pose(len(self._scan_node) - 1, self._est)

    def trajectory(self) -> NDArray[np.float64]:
        """Robot pose at every scan given (after the batch pass when ``batch_at_end``)."""
        est = self.optimized() if self.config.batch_at_end else self._est
        n = len(self._scan_node)
        out = np.empty((n, 3))
        for i in range(n):
            out[i] = self._robot_pose(i, est)
        if n:
            out[:, 2] = wrap_angle(out[:, 2])
        return out

    def used(self) -> NDArray[np.bool_]:
        """Per scan given: whether it is a node whose scan went into the map."""
        return self._used.values.copy()

    def grid(self) -> Any:
        """None: the caller builds the map from `trajectory` and `used` (`build_map`)."""
        return None

    def snapshot(self) -> FinishedGraph:
        """The results as they are now, picklable, without the solver (`FinishedGraph`)."""
        return FinishedGraph.of_graph(self)

    # ------------------------------------------------------------------ graph
    def node_poses(self, *, optimized: bool = True) -> NDArray[np.float64]:
        """Sensor poses of the nodes ``(M, 3)`` (batch-optimised when asked and enabled)."""
        if optimized and self.config.batch_at_end:
            return self.optimized().copy()
        return self._est.copy()

    def node_scan_indices(self) -> NDArray[np.int64]:
        """Scan index of every node."""
        return np.array([n.scan_index for n in self._nodes], dtype=np.int64)

    def _robot_pose(self, i: int, est: NDArray[np.float64]) -> NDArray[np.float64]:
        k = int(self._scan_node[i])
        node = self._nodes[k]
        robot = compose(est[k], inverse(self.laser_offset))
        return compose(robot, relative(node.odom, self._scan_odom[i]))

    def _node(
        self, index: int, scan: LaserScan, odom: NDArray[np.float64], path: float
    ) -> GraphNode:
        """A node of scan ``index`` (not accepted yet), holding its points and outline."""
        sensor_odom = compose(odom, self.laser_offset)
        node = GraphNode(index, odom.copy(), scan, self._shape, False, path, sensor_odom)
        node.hold()
        return node

    def _settle(self, k: int) -> None:
        """Node ``k`` is done: keep its arrays only while it may be in a local map."""
        node = self._nodes[k]
        if not node.accepted:
            node.release()  # never in a map: nothing reads its arrays again
            return
        self._held.append(k)
        while len(self._held) > self.config.local_map_nodes:
            self._nodes[self._held.popleft()].release()

    def set_motion_covariance(self, covariance: ArrayLike | None) -> None:
        """The covariance ``(3, 3)`` of the next scan's odometry step (the fused motion's).

        Compounded between nodes into the odometry factor's noise with
        ``odometry_noise: fused`` (`scanguard.slam.graph.odometry`); None: unknown.
        """
        self._next_cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)

    def _odom_noise(self, inc: NDArray[np.float64], usable: bool = True) -> Any:
        cfg = self.config
        if cfg.odometry_is_prior:
            return self._gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0, 1.0, 1.0]))
        # a node whose scan the guard dropped has no match factor: nothing but its step holds
        # it, so the step's own (fused) covariance, not the loose model that a match outvotes
        fused_here = cfg.odometry_noise == "fused" or not usable
        fused = self._steps.sensor_covariance() if fused_here else None
        if fused is not None:
            # the floors keep a step the matches pinned to a micrometre from outvoting the map
            floor = np.array([cfg.odom_floor_xy, cfg.odom_floor_xy, cfg.odom_floor_theta]) ** 2
            cov = fused * cfg.fused_noise_scale**2 + np.diag(floor)
            return self._gtsam.noiseModel.Gaussian.Covariance(cov)
        d = math.hypot(inc[0], inc[1])
        a = abs(float(wrap_angle(inc[2])))
        sxy = cfg.odom_floor_xy + cfg.odom_sigma_xy * d
        sth = cfg.odom_floor_theta + cfg.odom_sigma_theta * a + cfg.odom_sigma_theta_per_m * d
        return self._gtsam.noiseModel.Diagonal.Sigmas(np.array([sxy, sxy, sth]))

    def _add_node(
        self, index: int, scan: LaserScan, odom: NDArray[np.float64], *, usable: bool
    ) -> bool:
        if not self._nodes:
            return self._add_first_node(index, scan, odom, usable=usable)
        gtsam = self._gtsam
        k = len(self._nodes)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        prev = self._nodes[-1]
        robot_inc = relative(prev.odom, odom)
        # sensor-frame increment: the graph's variables are laser poses
        inc = compose(compose(inverse(self.laser_offset), robot_inc), self.laser_offset)
        predicted = compose(self._est[k - 1], inc)
        noise = self._odom_noise(inc, usable)
        odom_factor = gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*inc), noise)
        graph.add(odom_factor)
        essential = gtsam.NonlinearFactorGraph()
        essential.add(odom_factor)
        self.edges.append((k - 1, k, EDGE_ODOMETRY))
        initial = predicted
        node = self._node(index, scan, odom, prev.path + math.hypot(inc[0], inc[1]))
        if not usable:
            self.stats["scans_rejected_by_guard"] += 1
        elif len(node.points) >= 3:
            initial, node.accepted = self._sequential_factor(graph, k, node, predicted)
        accepted = node.accepted
        values.insert(k, gtsam.Pose2(*initial))
        self._nodes.append(node)
        self._last_node_stamp = float(scan.stamp)
        self.stats["nodes"] = len(self._nodes)
        if (
            not self._solver.commit(graph, values, len(self._nodes), essential=essential)
            and accepted
        ):
            # the match factor was refused: the node stays, on odometry alone
            if self.edges and self.edges[-1] == (k - 1, k, EDGE_MATCH):
                self.edges.pop()
            self.stats["matches_added"] -= 1
            self.stats["matches_refused"] += 1
        if accepted and self.config.loop_closure:
            self._loop_step(k)
        self._settle(k)
        return accepted

    def _add_first_node(
        self, index: int, scan: LaserScan, odom: NDArray[np.float64], *, usable: bool
    ) -> bool:
        """Node 0, held by a tight prior at the initial pose."""
        gtsam = self._gtsam
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        pose0 = compose(self.initial_pose, self.laser_offset)
        graph.add(
            gtsam.PriorFactorPose2(
                0, gtsam.Pose2(*pose0), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))
            )
        )
        values.insert(0, gtsam.Pose2(*pose0))
        node = self._node(index, scan, odom, 0.0)
        node.accepted = accepted = usable and len(node.points) > 0
        self._nodes.append(node)
        self._settle(0)
        self._solver.commit(graph, values, len(self._nodes))
        self._last_node_stamp = float(scan.stamp)
        self.stats["nodes"] = 1
        return accepted

    def _sequential_factor(
        self, graph: Any, k: int, node: GraphNode, predicted: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], bool]:
        """Match ``node`` (number ``k``) to its local map; add the match factor when found.

        Returns:
            The node's initial estimate and whether its scan goes into the maps.
        """
        cfg = self.config
        t0 = time.perf_counter()
        local, pts = local_map_points(
            self._nodes, self._est, predicted, cfg, node.points, node.view, node.sensor_odom
        )
        if len(pts) < len(node.points):
            self.stats["moving_points_left_out"] += len(node.points) - len(pts)
            self.stats["nodes_with_moving_points"] += 1
        result = None if local is None else match_local(pts, local, predicted, cfg, self.stats)
        self.stats["time_match_s"] += time.perf_counter() - t0
        if local is None or (result is None and self._weak >= cfg.reseed_after_weak):
            # nothing recent to match against: this scan starts a new local map where
            # odometry puts it (Karto keeps every scan in its running buffer likewise)
            self._weak = 0
            self.stats["local_map_seeds"] += 1
            return predicted, True
        if result is None:
            self._weak += 1
            self.stats["matches_weak"] += 1
            return predicted, False
        matched, cov = result
        meas = relative(self._est[k - 1], matched)
        cov_b = rotate_cov(cov * cfg.match_covariance_scale, float(matched[2]))
        graph.add(
            self._gtsam.BetweenFactorPose2(
                k - 1,
                k,
                self._gtsam.Pose2(*meas),
                self._gtsam.noiseModel.Gaussian.Covariance(cov_b),
            )
        )
        self.edges.append((k - 1, k, EDGE_MATCH))
        self._weak = 0
        self.stats["matches_added"] += 1
        return matched, True

    def _loop_step(self, k: int) -> None:
        """Count accepted node ``k`` towards the next loop search; search when it is due."""
        if self._cooldown > 0:
            self._cooldown -= 1
            return
        self._since_search += 1
        if self._since_search >= self.config.loop_search_every:
            self._since_search = 0
            t0 = time.perf_counter()
            self._search_loop(k)
            self.stats["time_loop_s"] += time.perf_counter() - t0

    # ------------------------------------------------------------------ loop closures
    def _search_loop(self, k: int) -> None:
        kept = (self._submaps, self.config, self.stats, self._node_index, self._failures)
        candidates = loop_candidates(k, self._nodes, self._solver, *kept)
        for cand in candidates:
            if self.propose_closure(cand):
                self._cooldown = self.config.loop_cooldown_nodes
                return

    # ------------------------------------------------------------------ batch
    def optimized(self) -> NDArray[np.float64]:
        """Node sensor poses after a batch Levenberg-Marquardt pass (cached until the next node).

        With ``final_check`` on, accepted closures whose optimised residual exceeds
        ``final_check_sigma`` (Mahalanobis) are removed and the graph is optimised again.
        """
        if self._batch is not None:
            return self._batch
        if not self._nodes:
            return np.zeros((0, 3))
        gtsam = self._gtsam
        t0 = time.perf_counter()
        initial = self._solver.isam.calculateEstimate()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(50)
        result = gtsam.LevenbergMarquardtOptimizer(self._solver.graph, initial, params).optimize()
        if self.config.final_check:
            dropped = self._final_check(result)
            if dropped:
                result = gtsam.LevenbergMarquardtOptimizer(
                    self._solver.graph, result, params
                ).optimize()
        self._batch = self._solver.values_to_array(result, len(self._nodes))
        self.stats["time_batch_s"] += time.perf_counter() - t0
        return self._batch

    def __repr__(self) -> str:
        return (
            f"GraphBackend(nodes={len(self._nodes)}, scans={len(self._scan_node)}, "
            f"closures={int(self.stats['closures_accepted'])}/{len(self.closures)})"
        )
