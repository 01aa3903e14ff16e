"""How a loop closure enters the ``graph`` back end: judge, waiting queues, gate, robust factor.

`ClosureIntake` is the part of `scanguard.slam.graph.backend.GraphBackend` that takes a
candidate from the loop search (or from a caller) to the graph: the closure judge's verdict,
the two queues where a closure waits for company (a doubted one that agrees with others,
`ClosureAgreement`; an accepted one that claims a large correction, `ClosureConfirmation`),
the consistency gate, and the robust between-factor; after the batch pass, the optional final
check that removes closures the optimised graph contradicts.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import ConfigError
from scanguard.slam.graph.agreement import (
    TOO_FAR,
    ClosureAgreement,
    ClosureConfirmation,
    FarAgreement,
    far_culprits,
)
from scanguard.slam.graph.closure import (
    ClosureCandidate,
    ClosureJudge,
    ClosureLabelConfig,
    ClosureRecord,
    ClosureVerdict,
    label_record,
)
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.consistency import closure_consistent, final_residual_sigmas
from scanguard.slam.graph.local_map import GraphNode
from scanguard.slam.graph.loop_search import NodeIndex, SubmapCache
from scanguard.slam.graph.solver import PoseGraphSolver, closure_factor

logger = logging.getLogger(__name__)

#: Edge kinds of `GraphBackend.edges`.
EDGE_ODOMETRY = "odometry"
EDGE_MATCH = "match"
EDGE_LOOP = "loop"


class ClosureIntake:
    """Loop-closure intake of `GraphBackend` (a mixin: it reads and writes the back end's state)."""

    config: GraphConfig
    closure_judge: ClosureJudge
    closures: list[ClosureRecord]
    edges: list[tuple[int, int, str]]
    stats: dict[str, float]
    labels: ClosureLabelConfig
    _gtsam: Any
    _nodes: list[GraphNode]
    _solver: PoseGraphSolver
    _agreement: ClosureAgreement
    _confirmation: ClosureConfirmation
    _far: FarAgreement
    _loop_factor_index: dict[int, int]
    _submaps: SubmapCache
    _node_index: NodeIndex
    _batch: NDArray[np.float64] | None
    _reference_sensor: NDArray[np.float64] | None

    def propose_closure(self, candidate: ClosureCandidate) -> bool:
        """Judge a loop-closure candidate and, when accepted, add it to the graph.

        Args:
            candidate: The candidate (found by the search, or given by a caller).

        Returns:
            Whether it was added.

        Raises:
            ConfigError: The candidate names a node that does not exist.
        """
        n = len(self._nodes)
        if not (0 <= candidate.node < n and 0 <= candidate.target_node < n):
            raise ConfigError(
                f"closure candidate between nodes {candidate.target_node} and {candidate.node}: "
                f"the graph has {n} nodes"
            )
        self.stats["closure_candidates"] += 1
        t0 = time.perf_counter()
        verdict = self.closure_judge(candidate)
        self.stats["time_judge_s"] += time.perf_counter() - t0
        far = verdict.accepted and self._too_far(candidate)
        if far:
            self.stats["closures_far"] += 1
            verdict = ClosureVerdict(False, verdict.score, f"{verdict.judge}; {TOO_FAR}")
        record = ClosureRecord(candidate=candidate, verdict=verdict)
        label_record(record, self._reference_sensor, self.labels)
        queue = self._confirmation if verdict.accepted else self._far if far else self._agreement
        if not verdict.accepted or queue.eligible(record):  # refused, or waits for company
            self.closures.append(record)
            self.stats["closures_rejected" if not verdict.accepted else "closures_waited"] += 1
            return self._enter_agreeing(queue, record)
        return self.add_closure(record)

    def _too_far(self, candidate: ClosureCandidate) -> bool:
        """``closure_far_sigmas``: the claimed correction is large in metres and in sigmas."""
        far = self.config.closure_far_sigmas
        if far is None:
            return False
        # NaN (no prior, no covariance) never compares true: such a candidate is kept
        return bool(
            candidate.disagreement_sigmas > far
            and candidate.disagreement[0] > self.config.closure_far_m
        )

    def _enter_agreeing(self, queue: ClosureAgreement, record: ClosureRecord) -> bool:
        """Enter the group of agreeing waiting candidates that ``record`` completes, if any."""
        added = False
        group = queue.offer(record, self._solver.est)
        if group and queue is self._far:
            self._withdraw_contradicted(group)
        for rec in group:
            rec.agreed = True
            self.stats["closures_agreed"] += 1
            at = next(i for i in range(len(self.closures) - 1, -1, -1) if self.closures[i] is rec)
            added = self._enter(rec, at) or added
        return added

    def add_closure(self, record: ClosureRecord) -> bool:
        """Append an accepted closure to `closures` and enter it as a robust between-factor.

        `propose_closure` calls this after the judge; it is public so that a benchmark can
        enter closures the judge never saw (wrong closures injected on purpose) through the
        same path, with the same robust kernel and the same final check.

        Args:
            record: The closure (its candidate's nodes must exist).

        Returns:
            Whether the solver took the factor.
        """
        self.closures.append(record)
        return self._enter(record, len(self.closures) - 1)

    def _enter(self, record: ClosureRecord, at: int) -> bool:
        """The gate, then the robust factor, of ``record`` (``closures[at]``)."""
        gtsam = self._gtsam
        cfg = self.config
        candidate = record.candidate
        if not closure_consistent(record, self._solver.est, self._solver.isam, cfg):
            self.stats["closures_inconsistent"] += 1
            return False
        self.stats["closures_accepted"] += 1
        graph = closure_factor(
            gtsam,
            candidate.target_node,
            candidate.node,
            np.asarray(candidate.pose, dtype=np.float64),
            np.asarray(candidate.covariance, dtype=np.float64) * cfg.match_covariance_scale,
            cfg.robust_kernel,
            cfg.robust_scale,
        )
        index = self._solver.graph.size()
        if not self._solver.commit(graph, self._gtsam.Values(), len(self._nodes), refresh_all=True):
            self.stats["closures_accepted"] -= 1
            self.stats["closures_refused"] += 1
            return False
        self._loop_factor_index[at] = index
        # a closure moves old nodes: cached submaps were built from the old estimates
        self._submaps.clear()
        self._batch = None
        record.added = True
        self.edges.append((candidate.target_node, candidate.node, EDGE_LOOP))
        return True

    def _withdraw_contradicted(self, group: list[ClosureRecord]) -> None:
        """Before a far group enters: withdraw the closures in the graph it contradicts.

        Not by residuals after it entered: the robust kernel gives a far claim next to no
        weight while the wrong closure holds the graph, so the group cannot move it. By the
        loop through each closure and the group on the wheels' (fused) poses instead
        (`far_culprits`), where the wrong closure stands out and the graph's bend does not.
        """
        in_graph = {at: self.closures[at] for at in self._loop_factor_index}
        odom = np.array([n.sensor_odom for n in self._nodes], dtype=np.float64)
        path, _ = self._node_index.arrays(self._nodes, len(self._nodes))
        out = far_culprits(group, in_graph, odom, path, self.labels)
        if not out:
            return
        for at in out:
            self.closures[at].withdrawn = True
        self._solver.withdraw([self._loop_factor_index.pop(at) for at in out], len(self._nodes))
        self.stats["closures_withdrawn"] += len(out)
        self._submaps.clear()
        self._batch = None
        logger.info("a far group agreed: %d loop closure(s) it contradicts withdrawn", len(out))

    def _final_check(self, values: Any) -> int:
        est = self._solver.values_to_array(values, len(self._nodes))
        dropped = 0
        for rec_index, factor_index in list(self._loop_factor_index.items()):
            rec = self.closures[rec_index]
            if final_residual_sigmas(rec.candidate, est) > self.config.final_check_sigma:
                self._solver.graph.remove(factor_index)
                del self._loop_factor_index[rec_index]
                rec.dropped_final = True
                dropped += 1
        if dropped:
            self.stats["closures_dropped_final"] += dropped
            logger.info("final check: %d loop closure(s) dropped after optimisation", dropped)
        return dropped
