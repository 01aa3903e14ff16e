"""The gate: the one place a verdict becomes accept or reject; and the judge's verdict."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from scanguard.errors import ConfigError
from scanguard.pairs.labels import FAULT, NORMAL
from scanguard.slam.gate import Gate, NonFiniteWatch
from scanguard.slam.judge import Judge, Verdict
from scanguard.slam.pair import Frame
from tests.helpers import make_sequence, room_segments

NAN = float("nan")


@pytest.mark.parametrize(
    ("kind", "p", "s", "accepted", "reason"),
    [
        ("none", 0.9, 0.9, True, "accepted"),
        ("cnn", 0.2, 0.9, True, "accepted"),
        ("cnn", 0.5, 0.0, False, "rejected_cnn"),
        ("cnn", NAN, 0.0, False, "rejected_cnn"),
        ("baseline", 0.9, 0.1, True, "accepted"),
        ("baseline", 0.0, NAN, False, "rejected_baseline"),
        ("both", 0.9, 0.1, False, "rejected_cnn"),
        ("both", 0.1, 0.9, False, "rejected_baseline"),
        ("both", 0.9, 0.9, False, "rejected_both"),
        ("both", 0.1, 0.1, True, "accepted"),
    ],
)
def test_gate_decides_on_the_verdict(kind, p, s, accepted, reason):
    d = Gate(kind, cnn_threshold=0.5, baseline_threshold=0.5).decide(Verdict(p, s))
    assert (d.accepted, d.reason) == (accepted, reason)


def test_oracle_reads_the_reference_label_and_nothing_judged_is_rejected():
    oracle = Gate("oracle")
    assert oracle.decide(Verdict(0.9, 0.9, reference_label=NORMAL)).accepted
    assert not oracle.decide(Verdict(0.0, 0.0, reference_label=FAULT)).accepted
    for kind in ("none", "cnn", "baseline", "both", "oracle"):
        assert not Gate(kind).decide(None).accepted  # skipped or no usable match
    # the unguarded instance of a run: every scan usable
    assert Gate("none", require_match=False).decide(None).accepted
    assert Gate("cnn", cnn_threshold=0.3).of_kind("baseline").cnn_threshold == 0.3
    with pytest.raises(ConfigError, match="unknown gate"):
        Gate("soft")  # type: ignore[arg-type]


def test_non_finite_watch_counts_and_warns_once(caplog):
    watch = NonFiniteWatch()
    with caplog.at_level(logging.WARNING, logger="scanguard.slam.gate"):
        for k in range(3):
            watch(Verdict(NAN, None), k)
        watch(Verdict(0.1, float("inf")), 3)
        watch(None, 4)
    assert watch.count == 4
    assert len([r for r in caplog.records if "treating the match" in r.getMessage()]) == 2


def test_judge_asks_only_the_detectors_it_was_given():
    seq = make_sequence(room_segments(), np.zeros((2, 3)))
    prev, cur = Frame.of(seq.scans[0]), Frame.of(seq.scans[1])

    class Match:
        pose = np.zeros(3)

    class Cnn:
        threshold = 0.5

        def fault_probability(self, previous, current, pose):
            return 0.25

    v = Judge(Cnn())(prev, cur, Match())
    assert v.fault_probability == 0.25 and v.baseline_score is None and np.isnan(v.score)
    assert Judge()(prev, cur, Match()) == Verdict()


def test_a_judge_without_odometry_sees_the_match_geometry_alone():
    """``use_odometry=False``: the shipped detector reads the pair as one without odometry."""
    from scanguard.detect.detector import FaultDetector
    from scanguard.matching.registry import get_matcher

    det = FaultDetector.load(backend="torch")
    assert det.reads_odometry
    seq = make_sequence(room_segments(), np.array([[0.2, 0.0, 0.05]]))
    prev, cur = Frame.of(seq.scans[0]), Frame.of(seq.scans[1])
    match = get_matcher("icp-paper")(cur.points, prev.points, None)
    lying = np.array([-0.6, 0.0, -0.3])  # wheels report backing up and turning the other way
    told = Judge(det)(prev, cur, match, lying).fault_probability
    blind = Judge(det, use_odometry=False)(prev, cur, match, lying).fault_probability
    none = Judge(det)(prev, cur, match, None).fault_probability
    assert blind == none  # the odometry is masked exactly as for a robot without one
    assert told is not None and blind is not None and told > blind


def test_the_wheels_arbitrate_only_degenerate_matches():
    """``odometry_below_eig``: the odometry reaches the detector only for a weakly
    constrained match (``eig_min_per_inlier`` below the bound), e.g. along a corridor."""
    seq = make_sequence(room_segments(), np.zeros((2, 3)))
    prev, cur = Frame.of(seq.scans[0]), Frame.of(seq.scans[1])

    class Match:
        pose = np.zeros(3)

        def __init__(self, eig: float) -> None:
            self.eig = eig

        def metrics(self) -> dict[str, float]:
            return {"eig_min_per_inlier": self.eig}

    judge = Judge(None, use_odometry=False, odometry_below_eig=0.1)
    assert judge._reads_odometry(Match(0.02)) and not judge._reads_odometry(Match(0.3))
    assert judge._reads_odometry(Match(float("nan")))  # unknown geometry: ask the wheels
    assert not Judge(None, use_odometry=False)._reads_odometry(Match(0.02))
    assert Judge(None)._reads_odometry(Match(0.3))
    assert Judge(None)(prev, cur, Match(0.3)) == Verdict()
