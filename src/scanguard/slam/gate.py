"""The gate: the one place where a `scanguard.slam.judge.Verdict` becomes accept or reject.

Kinds (`GateKind`):

* ``none`` - accept every judged pair (unguarded). With ``require_match=False`` it also
  accepts a scan without a verdict (skipped, or its match failed): every scan is usable, the
  back end's own matching decides (the unguarded back-end instance of a run);
* ``cnn`` - reject when the CNN's fault probability reaches its threshold;
* ``baseline`` - reject when the classical score reaches its threshold;
* ``both`` - reject when either flags the pair;
* ``oracle`` - reject when the reference labels the match a fault (``Verdict.reference_label``).

A probability or score that is not finite (a broken model outputs NaN) counts as a fault:
fail-safe. `NonFiniteWatch` counts such verdicts and warns once. A gate that weights a match
by its verdict (``soft``) would add a ``weight`` to `GateDecision`; the kinds above weight 0 or 1.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Literal, get_args

from scanguard.errors import ConfigError
from scanguard.pairs.labels import FAULT
from scanguard.slam.judge import Verdict

logger = logging.getLogger(__name__)

GateKind = Literal["none", "cnn", "baseline", "both", "oracle"]
#: The reason of a pair rejected by the wheel-support test (its back end drops the scan too).
REJECTED_WHEELS = "rejected_wheels"
GATE_KINDS: tuple[str, ...] = get_args(GateKind)


@dataclass(frozen=True)
class GateDecision:
    """Accept or reject, and why (``accepted``, ``rejected_<who>`` or ``no_verdict``)."""

    accepted: bool
    reason: str


def is_fault(value: float | None, threshold: float) -> bool:
    """``value >= threshold``; True for a missing or non-finite value (fail-safe)."""
    if value is None or not math.isfinite(value):
        return True
    return value >= threshold


@dataclass(frozen=True)
class Gate:
    """Turns verdicts into decisions (see the module docstring for the kinds).

    Attributes:
        kind: The gate kind.
        cnn_threshold: Fault threshold of the CNN probability.
        baseline_threshold: Fault threshold of the classical score.
        require_match: Reject a scan without a verdict (skipped or match failed); only the
            ``none`` kind may accept one (see the module docstring).
        wheel_support: The ``cnn`` and ``both`` kinds also reject a pair whose scan supports
            the wheels over the last matches (``Verdict.wheel_supported``:
            ``rejected_wheels``).
    """

    kind: GateKind = "cnn"
    cnn_threshold: float = 0.5
    baseline_threshold: float = 0.5
    require_match: bool = True
    wheel_support: bool = False

    def __post_init__(self) -> None:
        if self.kind not in GATE_KINDS:
            raise ConfigError(f"unknown gate {self.kind!r}: use one of {', '.join(GATE_KINDS)}")

    def of_kind(self, kind: GateKind, *, require_match: bool = True) -> Gate:
        """A gate of another kind with the same thresholds."""
        return replace(self, kind=kind, require_match=require_match)

    def decide(self, verdict: Verdict | None) -> GateDecision:
        """The decision on a verdict (None: nothing was judged, no usable match)."""
        if verdict is None:
            ok = self.kind == "none" and not self.require_match
            return GateDecision(ok, "accepted" if ok else "no_verdict")
        if self.kind == "none":
            return GateDecision(True, "accepted")
        if self.kind == "oracle":
            fault = verdict.reference_label == FAULT
            return GateDecision(not fault, "rejected_oracle" if fault else "accepted")
        flag_cnn = self.kind in ("cnn", "both") and is_fault(
            verdict.fault_probability, self.cnn_threshold
        )
        flag_base = self.kind in ("baseline", "both") and is_fault(
            verdict.baseline_score, self.baseline_threshold
        )
        if self.wheel_support and self.kind in ("cnn", "both") and verdict.wheel_supported:
            # first: the back end drops such a scan (its own match would follow it too)
            return GateDecision(False, REJECTED_WHEELS)
        if flag_cnn and flag_base:
            return GateDecision(False, "rejected_both")
        if flag_cnn or flag_base:
            return GateDecision(False, "rejected_cnn" if flag_cnn else "rejected_baseline")
        return GateDecision(True, "accepted")


@dataclass
class NonFiniteWatch:
    """Counts verdicts with a non-finite probability or score, and warns once per detector."""

    count: int = 0
    warned: set[str] = field(default_factory=set)

    def __call__(self, verdict: Verdict | None, index: int) -> None:
        """Look at the probability and score the judge computed for scan ``index``."""
        if verdict is None:
            return
        for who, value in (
            ("CNN", verdict.fault_probability),
            ("baseline", verdict.baseline_score),
        ):
            if value is None or math.isfinite(value):
                continue
            self.count += 1
            if who not in self.warned:
                self.warned.add(who)
                logger.warning(
                    "scan %d: the %s's fault %s is %s; treating the match as a fault (reported "
                    "once per guard; see n_non_finite)",
                    index,
                    who,
                    "probability" if who == "CNN" else "score",
                    value,
                )
