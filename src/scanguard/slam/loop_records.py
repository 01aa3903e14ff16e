"""What the per-scan loop records of a pass, and what an observer sees of each scan.

`LoopStep` is one row of ``decisions.csv``; `LoopResult` the whole pass; `StepView` and
`LoopObserver` what a sink (an MCAP file, a live view) is shown after every scan. The loop
itself is `scanguard.slam.loop.RunLoop`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from scanguard.scan import LaserScan, ScanSequence
from scanguard.slam.gate import GateDecision
from scanguard.slam.guard import GuardCounts, JudgedPair
from scanguard.slam.judge import Verdict
from scanguard.slam.motion import MotionStep


@dataclass(slots=True)
class LoopStep:
    """What the loop did with one scan (a row of ``decisions.csv``).

    Attributes:
        index: Scan index.
        stamp: Scan stamp (s).
        accepted: The ``+cnn`` instance's gate (the guard's policy) accepted the scan.
        reason: ``first``, ``accepted``, ``rejected_<who>``, ``match_failed`` or ``skipped``.
        match: The matcher's result (None: first, skipped or failed), while the step is
            seen (``on_step``, the observer); None in `LoopResult.steps`, which keep only the
            numbers ``decisions.csv`` needs (``reason`` says whether there was a match).
        verdict: The judge's verdict with the reference label (None without a match).
        match_increment: Robot-frame increment of the match (NaN without one).
        centroid_match: Paper Fig. 19 error of the match (m, NaN without one).
        timings: Seconds of ``match``, ``detect``, ``baseline`` and ``total`` (the guard's).
        motion: The ``+cnn`` instance's fused motion of this step (``motion: fused`` only):
            which sources moved it, and whether the wheels were flagged. In
            `LoopResult.steps` its ``increment`` and ``covariance`` are dropped (NaN, one
            shared read-only array each): ``decisions.csv`` needs neither.
    """

    index: int
    stamp: float
    accepted: bool
    reason: str
    match: Any
    verdict: Verdict | None
    match_increment: NDArray[np.float64]
    centroid_match: float
    timings: dict[str, float]
    motion: MotionStep | None = None

    @property
    def judged(self) -> bool:
        """Not skipped (the first scan counts as judged, as in ``decisions.csv``)."""
        return self.reason != "skipped"

    @property
    def fault_probability(self) -> float:
        """CNN fault probability (NaN when not computed)."""
        return float("nan") if self.verdict is None else self.verdict.probability

    @property
    def baseline_score(self) -> float:
        """Classical fault score (NaN when not computed)."""
        return float("nan") if self.verdict is None else self.verdict.score


@dataclass
class LoopResult:
    """What the loop recorded.

    Attributes:
        steps: One `LoopStep` per scan.
        labels: Scan index -> reference label of its judged pair (empty without a reference).
        backend_seconds: Gate -> per-scan seconds of that instance's ``update``.
        wanted: Gate -> per scan: whether that instance wanted the scan judged.
        counts: The guard's counts under its policy.
        non_finite: Verdicts with a non-finite probability or score.
        motion: Gate -> that instance's fused-motion counts (``match``, ``vouched_match``,
            ``wheels``, ``flagged``, ``prediction_only``: steps that used each source; see
            `scanguard.slam.motion.FusedMotion`) and its fitted wheel
            noise scales ``wheel_scale_x|y|theta`` (``motion: fused`` only).
    """

    steps: list[LoopStep] = field(default_factory=list)
    labels: dict[int, int] = field(default_factory=dict)
    backend_seconds: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    wanted: dict[str, NDArray[np.bool_]] = field(default_factory=dict)
    counts: GuardCounts = field(default_factory=GuardCounts)
    non_finite: int = 0
    motion: dict[str, dict[str, float]] = field(default_factory=dict)


OnStep = Callable[[LoopStep, int, int], None]

_NAN3 = np.full(3, np.nan)
_NAN3.flags.writeable = False
_NAN33 = np.full((3, 3), np.nan)
_NAN33.flags.writeable = False


def without_arrays(motion: MotionStep | None) -> MotionStep | None:
    """A copy of ``motion`` without its increment and covariance (what a step keeps)."""
    return None if motion is None else replace(motion, increment=_NAN3, covariance=_NAN33)


@dataclass(frozen=True)
class StepView:
    """What an observer sees of one scan, after every instance was updated with it.

    Attributes:
        scan: The scan.
        step: What the loop did with it (the guard's policy, as in ``decisions.csv``).
        pair: The scan, the previous one, the match and the odometry increment.
        decisions: Gate -> the decision of that instance's gate.
        usable: Gate -> the instance could use the scan (its gate accepted it, or the first).
        wanted: Gate -> the instance wanted the scan (GMapping and the graph skip some).
        poses: Gate -> that instance's robot pose after the scan.
    """

    scan: LaserScan
    step: LoopStep
    pair: JudgedPair
    decisions: Mapping[str, GateDecision]
    usable: Mapping[str, bool]
    wanted: Mapping[str, bool]
    poses: Mapping[str, NDArray[np.float64]]


class LoopObserver(Protocol):
    """Sees a run as it goes (a sink: an MCAP file, a live view); never changes it.

    `begin` before the first scan, `step` after every scan, `end` once after the loop with
    each instance's final trajectory and map (what the run writes as TUM and PGM files).
    """

    def begin(self, seq: ScanSequence, names: Mapping[str, str]) -> None:
        """The recording (scans, stamps, laser offset, reference) and gate -> instance name."""

    def step(self, view: StepView) -> None:
        """One scan (see `StepView`)."""

    def end(
        self, trajectories: Mapping[str, NDArray[np.float64]], grids: Mapping[str, Any]
    ) -> None:
        """Gate -> final robot trajectory ``(N, 3)`` and final `OccupancyGrid`."""
