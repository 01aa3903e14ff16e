"""Refused closures that agree, entered together (`scanguard.slam.graph.agreement`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.geometry import compose, relative
from scanguard.slam.graph import GraphConfig
from scanguard.slam.graph.agreement import ClosureAgreement, loop_error
from scanguard.slam.graph.closure import (
    ClosureCandidate,
    ClosureLabelConfig,
    ClosureRecord,
    ClosureVerdict,
)
from tests.test_graph import _run, ring  # noqa: F401 (the fixture)

# the graph's estimates: two old nodes 1 m apart, two new ones that drifted 0.5 m in y
EST = np.array(
    [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.1, 2.0, 0.0], [1.1, 2.0, 0.0], [2.1, 2.0, 0.1]]
)
TRUE_NEW = EST[2:] + np.array([0.0, 0.5, 0.0])


def _record(
    node: int, target: int, pose: np.ndarray, p: float = 0.3, accepted: bool = False
) -> ClosureRecord:
    # a real candidate: records then compare arrays, which a queue must never ask `==` of
    cand = ClosureCandidate(
        node=node,
        target_node=target,
        scan_index=node,
        target_scan_index=target,
        pose=np.asarray(pose, dtype=float),
        score=0.5,
        coarse_score=0.5,
        covariance=np.eye(3) * 1e-4,
        source=None,  # type: ignore[arg-type]
        target=None,  # type: ignore[arg-type]
    )
    return ClosureRecord(cand, ClosureVerdict(accepted, p, "learned"))


def _true(node: int, target: int, shift: tuple[float, float, float] = (0, 0, 0)) -> ClosureRecord:
    """A closure to where node ``node`` truly is (relative to the old node), moved by ``shift``."""
    truth = relative(EST[target], TRUE_NEW[node - 2])
    return _record(node, target, compose(truth, np.asarray(shift, dtype=float)))


def test_loop_error_is_zero_for_two_closures_that_claim_the_same_correction() -> None:
    a, b = _true(2, 0), _true(3, 1)
    dxy, dth = loop_error(a, b, EST)
    assert dxy == pytest.approx(0.0, abs=1e-12) and dth == pytest.approx(0.0, abs=1e-12)
    # each claims a 0.5 m correction of the graph, but one of them 0.3 m more along x
    dxy, dth = loop_error(a, _true(3, 1, (0.3, 0.0, 0.0)), EST)
    assert dxy == pytest.approx(0.3) and dth == pytest.approx(0.0, abs=1e-12)
    dxy, dth = loop_error(a, _true(3, 0, (0.0, 0.0, 0.02)), EST)
    assert dth == pytest.approx(0.02)
    # the same closure against itself closes exactly
    assert loop_error(a, a, EST)[0] == pytest.approx(0.0, abs=1e-12)


def _agreement(count: int = 3, window: int = 150) -> ClosureAgreement:
    cfg = GraphConfig(closure_agree_count=count, closure_agree_window=window)
    return ClosureAgreement(cfg, ClosureLabelConfig())


def test_three_agreeing_refused_closures_form_a_group_and_a_fourth_waits_again() -> None:
    agree = _agreement()
    first, second = _true(2, 0), _true(3, 1)
    assert agree.offer(first, EST) == []
    # a loner 0.4 m off, of the same scans as `second`: the queue must tell them apart by
    # identity (`==` on two records compares their pose arrays, and raises)
    assert agree.offer(_true(3, 1, (0.4, 0.0, 0.0)), EST) == []
    assert agree.offer(second, EST) == []
    assert agree.offer(_true(3, 0), EST) == []  # node 3 again: no new evidence
    third = _true(4, 0, (0.05, 0.0, 0.0))  # within a normal closure's 0.15 m
    group = agree.offer(third, EST)
    assert group == [third, first, second]
    assert agree.offer(_true(2, 1), EST) == []  # the group left: the loner and node 3 wait


def test_confident_refusals_and_accepted_closures_never_wait() -> None:
    agree = _agreement()
    for _ in range(3):
        assert agree.offer(_record(2, 0, relative(EST[0], TRUE_NEW[0]), p=0.9), EST) == []
    assert agree.offer(_record(2, 0, np.zeros(3), accepted=True), EST) == []
    assert not agree.eligible(_record(2, 0, np.zeros(3), p=float("nan")))
    off = _agreement(count=0)
    assert not off.eligible(_true(2, 0))


def test_waiting_closures_expire_after_the_window() -> None:
    agree = _agreement(count=2, window=10)
    est = np.vstack([EST, np.tile(EST[3], (20, 1))])
    assert agree.offer(_true(2, 0), est) == []
    late = _true(3, 1)
    late.candidate.node = 13  # 11 nodes after the first: it expired
    assert agree.offer(late, est) == []


class _Doubtful:
    """A learned judge that doubts every closure at fault probability ``p``."""

    name = "learned"

    def __init__(self, p: float) -> None:
        self.p = p

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        return ClosureVerdict(False, self.p, self.name)


@pytest.mark.parametrize("p", [0.3, 0.6])
def test_a_drifted_loop_closes_on_three_agreeing_doubted_closures(ring, p) -> None:  # type: ignore[no-untyped-def]  # noqa: F811
    ref, scans, _ = ring
    cfg = GraphConfig(loop_closure=False, closure_gate_sigmas=0, closure_agree_count=3)
    b = _run(ring, cfg, judge=_Doubtful(p), reject=range(len(scans)))  # odometry alone
    nodes = b.node_scan_indices()
    pairs = [(len(nodes) - 1 - k, k) for k in range(3)]  # the lap's end against its start
    before = b.node_poses()
    added = []
    for node, target in pairs:
        i, j = int(nodes[node]), int(nodes[target])
        truth = relative(ref[j], ref[i])
        assert np.hypot(*(relative(before[target], before[node]) - truth)[:2]) > 1.0
        cand = ClosureCandidate(
            node=node,
            target_node=target,
            scan_index=i,
            target_scan_index=j,
            pose=truth,
            score=0.9,
            coarse_score=0.9,
            covariance=np.diag([1e-4, 1e-4, 1e-6]),
            source=scans[i],
            target=scans[j],
        )
        added.append(b.propose_closure(cand))
    if p > cfg.closure_agree_max_p:  # the judge is confident: nothing waits, nothing enters
        assert added == [False] * 3 and b.stats["closures_agreed"] == 0
        return
    assert added == [False, False, True]
    assert b.stats["closures_agreed"] == 3 and b.stats["closures_accepted"] == 3
    assert all(r.agreed and r.added and not r.verdict.accepted for r in b.closures)
    after = b.node_poses()
    node, target = pairs[0]
    err = relative(
        relative(ref[int(nodes[target])], ref[int(nodes[node])]),
        relative(after[target], after[node]),
    )
    assert math.hypot(err[0], err[1]) < 0.05


def test_an_accepted_closure_claiming_a_large_correction_waits_for_confirmation() -> None:
    from dataclasses import replace

    from scanguard.slam.graph.agreement import ClosureConfirmation

    def accepted(rec: ClosureRecord) -> ClosureRecord:
        # the graph's own estimate of the pose, 0.2 m sure: the 0.5 m correction is 2.5 sigmas
        c = rec.candidate
        prior = relative(EST[c.target_node], EST[c.node])
        cand = replace(c, prior_pose=prior, prior_covariance=np.diag([0.04, 0.04, 0.01]))
        return ClosureRecord(cand, ClosureVerdict(True, 0.01, "learned"))

    cfg = GraphConfig(closure_confirm_sigmas=2.0)
    confirm = ClosureConfirmation(cfg, ClosureLabelConfig())
    first, second = accepted(_true(2, 0)), accepted(_true(3, 1))
    assert first.candidate.disagreement_sigmas == pytest.approx(2.5, rel=0.01)
    assert confirm.eligible(first)
    assert confirm.offer(first, EST) == []  # waits
    assert confirm.offer(accepted(_true(3, 1, (0.4, 0.0, 0.0))), EST) == []  # one door along
    group = confirm.offer(second, EST)
    assert [id(g) for g in group] == [id(second), id(first)]  # both enter, the newest first
    # a small correction enters at once; a refused one is the other queue's; off: never
    small = accepted(_true(2, 0, (0.0, -0.45, 0.0)))
    assert small.candidate.disagreement_sigmas < 2.0 and not confirm.eligible(small)
    assert not confirm.eligible(replace(first, verdict=ClosureVerdict(False, 0.9, "learned")))
    off = ClosureConfirmation(GraphConfig(closure_confirm_sigmas=None), ClosureLabelConfig())
    assert not off.eligible(first)


def test_far_culprits_names_the_closures_a_far_group_contradicts_on_the_wheels() -> None:
    from scanguard.slam.graph.agreement import far_culprits

    # path length (m) at each node: an old stretch (0-4), its revisit 100 m later (5-9), and
    # node 10 much later; the wheels' sensor poses follow the path, the revisit 3 m beside it
    path = np.array([0, 1, 2, 3, 12.5, 100, 101, 102, 103, 112.5, 190], dtype=float)
    odom = np.array([[p % 100 if p < 190 else 9, 3.0 * (p >= 100), 0.0] for p in path])

    def closure(node: int, target: int, off: float = 0.0) -> ClosureRecord:
        pose = compose(relative(odom[target], odom[node]), np.array([off, 0.0, 0.0]))
        return _record(node, target, pose, accepted=True)

    group = [closure(5, 0), closure(6, 1), closure(7, 2)]
    in_graph = {
        10: closure(8, 3),  # right, and the group agrees with it
        11: closure(8, 3, off=2.5),  # a room along: every member's loop misses by 2.5 m
        12: closure(10, 0, off=2.5),  # wrong too, but 90 m of path from all: unknown
        13: closure(8, 2, off=0.25),  # within a fault's 0.3 m plus the legs' drift
        14: closure(9, 4, off=2.5),  # no short loop with the group; agrees with 11
        15: closure(9, 4),  # right, near 11 but 2.5 m from it: not its company
    }
    labels = ClosureLabelConfig()
    assert far_culprits(group, in_graph, odom, path, labels) == [11, 14]
    del in_graph[11]  # without the contradicted one, 14 meets nothing that speaks against it
    assert far_culprits(group, in_graph, odom, path, labels) == []
    assert far_culprits(group, {}, odom, path, labels) == []


@pytest.mark.parametrize("agree", [3, 0])
def test_a_far_group_withdraws_the_wrong_closure_that_bent_the_graph(ring, agree) -> None:  # type: ignore[no-untyped-def]  # noqa: F811
    from dataclasses import replace

    ref, scans, _ = ring
    cfg = GraphConfig(
        loop_closure=False,
        closure_gate_sigmas=0,
        closure_confirm_sigmas=None,
        closure_far_sigmas=2.5,
        closure_far_agree=agree,
    )
    b = _run(ring, cfg, reject=range(len(scans)))  # odometry alone: the lap drifts
    nodes = b.node_scan_indices()
    last = len(nodes) - 1

    def truth(node: int, target: int) -> np.ndarray:
        return relative(ref[int(nodes[target])], ref[int(nodes[node])])

    def candidate(node: int, target: int, pose: np.ndarray) -> ClosureCandidate:
        est = b.node_poses()
        return ClosureCandidate(
            node=node, target_node=target, scan_index=int(nodes[node]),
            target_scan_index=int(nodes[target]), pose=pose, score=0.9, coarse_score=0.9,
            covariance=np.diag([1e-4, 1e-4, 1e-6]), source=scans[int(nodes[node])],
            target=scans[int(nodes[target])], prior_pose=relative(est[target], est[node]),
            prior_covariance=np.diag([0.3**2, 0.3**2, 0.01]),
        )  # fmt: skip

    # a wrong closure, one room (3 m) along, slipped in at the lap's end: the graph bends to it
    wrong = candidate(last - 4, 0, compose(truth(last - 4, 0), np.array([3.0, 0.0, 0.0])))
    wrong = replace(wrong, prior_pose=None, prior_covariance=None)  # entered as given
    assert b.propose_closure(wrong) and b.closures[-1].added
    # then the right closures of the next nodes all claim ~3 m beyond the graph's belief
    for k in range(3):
        right = candidate(last - 3 + k, k, truth(last - 3 + k, k))
        assert right.disagreement_sigmas > 2.5 and right.disagreement[0] > 1.5
        b.propose_closure(right)
    after = b.node_poses()
    err = relative(truth(last - 3, 0), relative(after[0], after[last - 3]))
    if not agree:  # off: the far claims stay refused, the wrong closure holds the graph
        assert b.stats["closures_far"] == 3 and b.stats["closures_withdrawn"] == 0
        assert math.hypot(err[0], err[1]) > 2.0
        return
    assert b.stats["closures_far"] == 3 and b.stats["closures_agreed"] == 3
    assert b.closures[0].withdrawn and b.stats["closures_withdrawn"] == 1
    assert all(r.added and r.agreed and not r.withdrawn for r in b.closures[1:])
    assert math.hypot(err[0], err[1]) < 0.05
    # the batch pass at the end solves the graph without it too
    final = b.optimized()
    err = relative(truth(last - 3, 0), relative(final[0], final[last - 3]))
    assert math.hypot(err[0], err[1]) < 0.05
