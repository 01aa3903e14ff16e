"""Closures the judge doubted, accepted when several of them agree (``closure_agree_count``).

After a drift of a metre or two the first closures of a revisit are right but move the graph
far, and session 20's learned judge, which read how far a closure would move the graph in
metres, called them doubtful (ACES, session 20: eight right candidates in a row refused at fault
probabilities 0.29-0.48, and the drift stayed). Each on its own is weak evidence; several
from different scans that claim the *same* correction are not (the idea of Olson's single
cluster and of Latif's RRR: a wrong closure rarely has company that agrees with it, a right
one does).

A refused candidate whose fault probability is below ``closure_agree_max_p`` waits here for
``closure_agree_window`` nodes. When ``closure_agree_count`` waiting candidates agree
pairwise, they enter the graph together, each through the same consistency gate and robust
kernel as any accepted closure. Two closures ``i`` and ``j`` agree when the loop

    node_i -> target_i (closure i, inverted) -> target_j (graph) -> node_j (closure j)
    -> node_i (graph)

closes within a normal closure's label thresholds (`ClosureLabelConfig`: 0.15 m, 1.5 deg):
they imply the same correction of the graph to within what a right closure may err.
Consistent wrong groups exist (a corridor matched one door further along, scan after scan);
the probability ceiling keeps the judge's confident refusals out (that group measured
0.98-0.99 on ACES), but not every one: on Intel groups of three at 0.27-0.32, 2.85 m off,
entered and cost 19 % over perturbed runs. Off by default (docs/graph.md, "Doubted closures
that agree").

`ClosureConfirmation` uses the same queue and test the other way round: a closure the judge
*accepted* that claims a correction beyond ``closure_confirm_sigmas`` standard deviations
waits for one agreeing candidate (the default since session 23: a wrong closure one room
along the corridor, accepted alone, folded a hospital-scale building at two search phases of
three; docs/graph.md, "Aliases and fragility").

`FarAgreement` keeps the candidates ``closure_far_sigmas`` refused (a correction large in
metres and in sigmas): a group of ``closure_far_agree`` of them enters, and the intake then
withdraws the closures the graph contradicts (docs/graph.md, "Closures that claim too much").
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import compose, inverse, relative, wrap_angle
from scanguard.slam.graph.closure import ClosureLabelConfig, ClosureRecord, DetectorClosureJudge
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.judges import LearnedClosureJudge

#: Judges whose score is a fault probability (the ceiling means something only for them).
PROBABILITY_JUDGES = frozenset({LearnedClosureJudge.name, DetectorClosureJudge.name})


def loop_error(a: ClosureRecord, b: ClosureRecord, est: NDArray[np.float64]) -> tuple[float, float]:
    """Translation (m) and rotation (rad) by which closures ``a`` and ``b`` fail to agree.

    The loop through both closures and the graph's current estimates (module docstring),
    taken in node ``a``'s frame.
    """
    ca, cb = a.candidate, b.candidate
    z_a = np.asarray(ca.pose, dtype=np.float64)
    z_b = np.asarray(cb.pose, dtype=np.float64)
    old = relative(est[ca.target_node], est[cb.target_node])
    new = relative(est[cb.node], est[ca.node])
    loop = compose(compose(compose(inverse(z_a), old), z_b), new)
    return float(math.hypot(loop[0], loop[1])), float(abs(wrap_angle(loop[2])))


class ClosureAgreement:
    """Doubted closures waiting for company (module docstring).

    Args:
        config: The graph's config (``closure_agree_*``).
        labels: The thresholds two agreeing closures must meet (a normal closure's).
    """

    def __init__(self, config: GraphConfig, labels: ClosureLabelConfig) -> None:
        self.count = int(config.closure_agree_count)
        self.max_p = float(config.closure_agree_max_p)
        self.window = int(config.closure_agree_window)
        self.max_xy = float(labels.normal_translation)
        self.max_theta = math.radians(labels.normal_rotation_deg)
        self._waiting: deque[ClosureRecord] = deque()

    def eligible(self, record: ClosureRecord) -> bool:
        """A refused candidate this may keep: a probability judge's, below the ceiling."""
        v = record.verdict
        return (
            self.count > 1
            and not v.accepted
            and v.judge in PROBABILITY_JUDGES
            and math.isfinite(v.score)
            and v.score < self.max_p
        )

    def offer(self, record: ClosureRecord, est: NDArray[np.float64]) -> list[ClosureRecord]:
        """Keep a refused ``record``; the group it completes, if any (itself first).

        Candidates older than ``window`` nodes before ``record``'s are forgotten first. A
        group is ``record`` and the waiting candidates of other nodes that agree with it and
        with each other (the earliest first, greedily); its members leave the queue.
        """
        if not self.eligible(record):
            return []
        newest = record.candidate.node
        while self._waiting and newest - self._waiting[0].candidate.node > self.window:
            self._waiting.popleft()
        group = [record]
        for other in self._waiting:
            # company from other scans: one scan matched twice is one piece of evidence
            if any(other.candidate.node == g.candidate.node for g in group):
                continue
            if all(self._agree(other, g, est) for g in group):
                group.append(other)
        if len(group) < self.count:
            self._waiting.append(record)
            return []
        # by identity: records compare their candidates' arrays, which `==` cannot decide
        members = {id(g) for g in group}
        self._waiting = deque(w for w in self._waiting if id(w) not in members)
        return group

    def _agree(self, a: ClosureRecord, b: ClosureRecord, est: NDArray[np.float64]) -> bool:
        dxy, dth = loop_error(a, b, est)
        return dxy <= self.max_xy and dth <= self.max_theta


class ClosureConfirmation(ClosureAgreement):
    """Accepted closures that claim a large correction, waiting for one that agrees.

    The same queue and the same agreement as `ClosureAgreement`, for candidates the judge
    *accepted* whose `disagreement_sigmas` exceeds ``closure_confirm_sigmas``: two that agree
    enter together (`GraphConfig.closure_confirm_sigmas`).
    """

    def __init__(self, config: GraphConfig, labels: ClosureLabelConfig) -> None:
        super().__init__(config, labels)
        self.limit = config.closure_confirm_sigmas
        self.count = 2

    def eligible(self, record: ClosureRecord) -> bool:
        """An accepted candidate whose claimed correction is beyond the limit.

        One without the graph's uncertainty (a caller's candidate with no prior, NaN) is not:
        nothing says how large its correction is.
        """
        s = record.candidate.disagreement_sigmas
        return self.limit is not None and record.verdict.accepted and s > self.limit


#: The verdict suffix of a closure refused by ``closure_far_sigmas`` (`ClosureIntake`).
TOO_FAR = "too far"


class FarAgreement(ClosureAgreement):
    """Closures refused as too far, waiting for a crowd that agrees (``closure_far_agree``).

    The same queue and the same agreement as `ClosureAgreement`, for candidates the judge
    accepted and ``closure_far_sigmas`` refused. A wrong alias keeps company for a few nodes
    (the office stand-in's alike rooms: groups of at most 5 over 30 seeds); once one wrong
    closure has moved the graph, every right one after it claims a correction far beyond the
    graph's uncertainty, scan after scan (58 in a row on office seed 47). A group of
    ``closure_far_agree`` says the graph, not the closures, is wrong.
    """

    def __init__(self, config: GraphConfig, labels: ClosureLabelConfig) -> None:
        super().__init__(config, labels)
        self.count = int(config.closure_far_agree)

    def eligible(self, record: ClosureRecord) -> bool:
        """A candidate refused only because the correction it claims is too far."""
        v = record.verdict
        return self.count > 1 and not v.accepted and v.judge.endswith(TOO_FAR)


#: How much the wheels' (fused) poses may drift along the two legs of a loop through two
#: closures, per metre of the legs (5 %: the fused motion of the office stand-in drifts 1-2 %).
FAR_LOOP_DRIFT = 0.05
#: Each leg of such a loop (target to target, node to node) at most this long (m): the
#: allowance then stays under 1.3 m, below the 3 m of a room along, which it must not hide.
FAR_LOOP_PATH_M = 10.0


def _short_loop(a: ClosureRecord, b: ClosureRecord, path: NDArray[np.float64]) -> float | None:
    """The path length of the loop through ``a`` and ``b`` (m), None when either leg is long."""
    ca, cb = a.candidate, b.candidate
    p_t = abs(path[ca.target_node] - path[cb.target_node])
    p_n = abs(path[ca.node] - path[cb.node])
    if p_t > FAR_LOOP_PATH_M or p_n > FAR_LOOP_PATH_M:
        return None
    return float(p_t + p_n)


def far_culprits(
    group: list[ClosureRecord],
    in_graph: dict[int, ClosureRecord],
    odom: NDArray[np.float64],
    path: NDArray[np.float64],
    labels: ClosureLabelConfig,
) -> list[int]:
    """The closures in the graph that a far group contradicts (their keys in ``in_graph``).

    Loops are taken on the wheels' (fused) poses ``odom`` and only where both legs (target
    to target, node to node) are at most `FAR_LOOP_PATH_M` of path: two closures *agree*
    when their loop misses by at most a fault's translation plus `FAR_LOOP_DRIFT` of the
    legs. A closure contradicts the group when it disagrees with most of the members it
    shares a short loop with (it and the group cannot both be right, and the group is many);
    then so does every closure that agrees with a contradicted one (a wrong cluster claims
    one wrong correction along the whole revisit, and only its newest part meets the group).
    Closures that share no short loop with either are left alone: the wheels say nothing
    about them.

    Args:
        group: The far group about to enter.
        in_graph: The closures in the graph, by their index in the back end's list.
        odom: Sensor pose of every node on the wheels' (fused) odometry ``(n, 3)``.
        path: Odometry path length at every node (m).
        labels: The closure label thresholds (a fault's translation).
    """

    def agree(a: ClosureRecord, b: ClosureRecord, legs: float) -> bool:
        miss, _ = loop_error(a, b, odom)
        return miss <= labels.fault_translation + FAR_LOOP_DRIFT * legs

    out: set[int] = set()
    for at, rec in in_graph.items():
        loops = [(g, legs) for g in group if (legs := _short_loop(rec, g, path)) is not None]
        if loops and 2 * sum(not agree(rec, g, legs) for g, legs in loops) > len(loops):
            out.add(at)
    grown = True
    while grown:  # the company of a contradicted closure
        grown = False
        for at, rec in in_graph.items():
            if at in out:
                continue
            for k in list(out):
                legs = _short_loop(rec, in_graph[k], path)
                if legs is not None and agree(rec, in_graph[k], legs):
                    out.add(at)
                    grown = True
                    break
    return sorted(out)
