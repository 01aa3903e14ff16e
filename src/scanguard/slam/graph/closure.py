"""Loop-closure candidates, their reference labels, and the judges that accept or reject them.

A loop-closure search (`scanguard.slam.graph.GraphBackend`) proposes a `ClosureCandidate`: the
pose of the current scan's sensor frame in the frame of an older node (the centre of the
matched submap), with the matcher's response and covariance. Before the candidate becomes a
factor of the pose graph, a `ClosureJudge` decides:

* `AcceptAll` (``none``): every candidate the search returns (responses at or above
  ``loop_min_response``) is accepted: what a graph SLAM does without any check;
* `ResponseTest` (``classical``): Karto's / slam_toolbox's test: the fine response at or above a
  minimum and the response-surface standard deviations at or below a maximum;
* `DetectorClosureJudge` (``cnn``): the fault detector renders the current scan against the
  candidate node's scan at the proposed pose, exactly as it renders a sequential pair, and
  rejects the candidate when its fault probability reaches the threshold;
* `ReferenceClosureJudge` (``oracle``): accepts only candidates whose reference label is normal.

Labels (`closure_label`) come from the reference poses with the thresholds of
`ClosureLabelConfig`: a candidate is a **fault** when its proposed relative pose is more than
``fault_translation`` (0.3 m) or ``fault_rotation_deg`` (3 deg) from the reference relative
pose, **normal** when it is within ``normal_translation`` (0.15 m) and ``normal_rotation_deg``
(1.5 deg), and **ambiguous** in between. The fault limits are the issue's acceptance bound: no
accepted closure may be further from the reference than that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, model_validator

from scanguard.config import YamlModel
from scanguard.geometry import as_pose, relative, wrap_angle
from scanguard.matching.registry import get_matcher
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL
from scanguard.scan import LaserScan
from scanguard.slam.graph.solver import rotate_cov


class ClosureLabelConfig(YamlModel):
    """Thresholds that label a loop-closure candidate against the reference.

    Attributes:
        fault_translation: Translation error (m) above which a candidate is a fault.
        normal_translation: Translation error (m) below which it may be normal.
        fault_rotation_deg: Rotation error (deg) above which it is a fault.
        normal_rotation_deg: Rotation error (deg) below which it may be normal.
    """

    fault_translation: float = Field(default=0.3, gt=0.0)
    normal_translation: float = Field(default=0.15, gt=0.0)
    fault_rotation_deg: float = Field(default=3.0, gt=0.0)
    normal_rotation_deg: float = Field(default=1.5, gt=0.0)

    @model_validator(mode="after")
    def _ordered(self) -> ClosureLabelConfig:
        if self.normal_translation > self.fault_translation:
            raise ValueError("need normal_translation <= fault_translation")
        if self.normal_rotation_deg > self.fault_rotation_deg:
            raise ValueError("need normal_rotation_deg <= fault_rotation_deg")
        return self


class ClosureJudgeConfig(YamlModel):
    """Settings of the closure judges (one per gate of a run).

    Attributes:
        cnn_threshold: Fault-probability threshold of the detector on closures (None = the
            detector's own threshold, chosen on sequential pairs).
        classical_min_response: `ResponseTest`: minimum fine response (0..1).
        classical_max_std_xy: `ResponseTest`: maximum standard deviation in x and y (m).
        classical_max_std_theta: `ResponseTest`: maximum standard deviation in heading (rad).
        labels: Reference labelling of candidates (oracle and reports).
        judge_file: A closure-judge file (`scanguard.slam.graph.judges.save_closure_judge`,
            e.g. from ``benchmarks/closure_judge.py --model``) whose learned judge is the
            ``cnn`` gate's and whose classical test is the ``baseline`` gate's; None = the
            shipped ``scanguard/models/closure_judge.json``.
        cnn_with_classical: The ``cnn`` gate accepts a closure only when the classical test
            of the same file accepts it too (`AllOf`: precision first).
    """

    cnn_threshold: float | None = Field(default=None, gt=0.0, lt=1.0)
    classical_min_response: float = Field(default=0.5, ge=0.0, le=1.0)
    classical_max_std_xy: float = Field(default=0.05, gt=0.0)
    classical_max_std_theta: float = Field(default=0.02, gt=0.0)
    labels: ClosureLabelConfig = Field(default_factory=ClosureLabelConfig)
    judge_file: Path | None = None
    cnn_with_classical: bool = False


@dataclass
class ClosureCandidate:
    """A proposed loop closure: the current node seen from an older node.

    Attributes:
        node: Index of the current node.
        target_node: Index of the older node (the centre of the matched submap).
        scan_index: Index of the current node's scan among the scans given to the back end.
        target_scan_index: Index of the target node's scan.
        pose: Proposed pose ``(x, y, theta)`` of the current sensor frame in the target node's
            sensor frame.
        score: Fine response at ``pose`` (0..1).
        coarse_score: Response of the wide coarse search.
        covariance: Response-surface covariance of ``pose`` (3x3, target frame).
        source: The current scan.
        target: The target node's scan.
        match: The refined match (`scanguard.matching.MatchResult`) when there is one; a
            detector that reads ICP metrics needs it.
        prior_pose: The graph's estimate of the same relative pose when the candidate was
            proposed (what the picture cannot show: how far the closure would move the graph).
        path_gap: Path length (m) travelled from the target node to the current node (drift
            grows with it).
        prior_covariance: The graph's uncertainty about ``prior_pose`` when the candidate was
            proposed (3x3, in the current node's frame, as gtsam perturbs a pose on the
            right; `scanguard.slam.graph.loop_search.relative_covariance`), None when gtsam
            could not form it.
        alias_pose: The best pose of the same coarse search at least
            ``GraphConfig.loop_alias_radius`` away from this one (a second peak: the next door
            along a corridor, an alike room), None when none scored at least
            ``loop_alias_min_ratio`` of the best or the search was not made.
        alias_ratio: Its coarse response over the best one's (0: none found that high; NaN:
            not searched).
    """

    node: int
    target_node: int
    scan_index: int
    target_scan_index: int
    pose: NDArray[np.float64]
    score: float
    coarse_score: float
    covariance: NDArray[np.float64]
    source: LaserScan
    target: LaserScan
    match: Any = None
    prior_pose: NDArray[np.float64] | None = None
    path_gap: float = float("nan")
    prior_covariance: NDArray[np.float64] | None = None
    alias_pose: NDArray[np.float64] | None = None
    alias_ratio: float = float("nan")

    @property
    def disagreement(self) -> tuple[float, float]:
        """Translation (m) and rotation (rad) between the proposed and the prior relative pose."""
        if self.prior_pose is None:
            return float("nan"), float("nan")
        e = relative(as_pose(self.prior_pose), as_pose(self.pose))
        return float(math.hypot(e[0], e[1])), float(abs(wrap_angle(e[2])))

    @property
    def disagreement_sigmas(self) -> float:
        """The correction the closure claims, in standard deviations of what the graph allows.

        The Mahalanobis length of the proposed pose against the prior one (in the current
        node's frame), under the graph's uncertainty about the prior plus the match's own:
        a correction after a long drift the graph knows about is small in these units, the
        same metres after a short, certain path are large. NaN without a prior covariance.
        """
        return self._sigmas(self.pose)

    @property
    def alias_sigmas(self) -> float:
        """`disagreement_sigmas` of the alias pose (NaN without one).

        How far the graph's own uncertainty tells the alias from the prior.
        """
        return float("nan") if self.alias_pose is None else self._sigmas(self.alias_pose)

    @property
    def alias_distance(self) -> float:
        """Distance (m) from the proposed pose to the alias (NaN without one)."""
        if self.alias_pose is None:
            return float("nan")
        return float(math.hypot(*(np.asarray(self.alias_pose)[:2] - np.asarray(self.pose)[:2])))

    def _sigmas(self, pose: NDArray[np.float64]) -> float:
        if self.prior_pose is None or self.prior_covariance is None:
            return float("nan")
        e = relative(as_pose(self.prior_pose), as_pose(pose))
        e[2] = wrap_angle(e[2])
        # the match's covariance is in the target's frame; gtsam's closure factor rotates
        # it the same way (`scanguard.slam.graph.solver.closure_factor`)
        cov = np.asarray(self.prior_covariance, dtype=np.float64) + rotate_cov(
            np.asarray(self.covariance, dtype=np.float64), float(self.pose[2])
        )
        try:
            d2 = float(e @ np.linalg.solve(cov, e))
        except np.linalg.LinAlgError:
            return float("nan")
        return math.sqrt(d2) if d2 >= 0.0 and math.isfinite(d2) else float("nan")

    @property
    def std(self) -> NDArray[np.float64]:
        """Standard deviations ``(sx, sy, stheta)`` from the covariance diagonal."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))


@dataclass(frozen=True)
class ClosureVerdict:
    """A judge's decision on one candidate.

    Attributes:
        accepted: The candidate may enter the graph.
        score: The judge's score (fault probability for the detector, response otherwise).
        judge: Name of the judge.
    """

    accepted: bool
    score: float
    judge: str


@dataclass
class ClosureRecord:
    """What happened to one candidate (`GraphBackend.closures`).

    Attributes:
        candidate: The candidate (with its scans: the closure-judge harvest reads them).
        verdict: The judge's verdict.
        added: It became a factor of the graph.
        dropped_final: The final check removed it after optimisation.
        withdrawn: Taken out of the graph during the run: a group of closures refused as too
            far agreed with each other, entered, and the graph then contradicted this one
            (``closure_far_agree``).
        inconsistent: Accepted by the judge, refused by the graph's consistency gate (its
            claim lies more than ``closure_gate_sigmas`` off the graph's uncertainty).
        gate_sigmas: How far off, in those standard deviations (NaN: gate off).
        agreed: Entered with a group of waiting candidates that agree with each other
            (`scanguard.slam.graph.agreement`): refused by the judge, or accepted but claiming
            a correction that needed confirming (``closure_confirm_sigmas``).
        label: Reference label (`closure_label`), when a reference was given.
        trans_error: Translation error against the reference (m), NaN without one.
        rot_error: Rotation error against the reference (rad), NaN without one.
    """

    candidate: ClosureCandidate
    verdict: ClosureVerdict
    added: bool = False
    dropped_final: bool = False
    withdrawn: bool = False
    inconsistent: bool = False
    gate_sigmas: float = float("nan")
    agreed: bool = False
    label: int = AMBIGUOUS
    trans_error: float = float("nan")
    rot_error: float = float("nan")
    extra: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Flat row for CSV / JSON."""
        c = self.candidate
        s = c.std
        return {
            "node": c.node,
            "target_node": c.target_node,
            "scan": c.scan_index,
            "target_scan": c.target_scan_index,
            "x": float(c.pose[0]),
            "y": float(c.pose[1]),
            "theta": float(c.pose[2]),
            "response": c.score,
            "coarse_response": c.coarse_score,
            "std_x": float(s[0]),
            "std_y": float(s[1]),
            "std_theta": float(s[2]),
            "disagreement_m": c.disagreement[0],
            "disagreement_rad": c.disagreement[1],
            "path_gap": c.path_gap,
            "disagreement_sigmas": c.disagreement_sigmas,
            "alias_ratio": c.alias_ratio,
            "alias_m": c.alias_distance,
            "alias_sigmas": c.alias_sigmas,
            "judge": self.verdict.judge,
            "judge_score": self.verdict.score,
            "accepted": self.verdict.accepted,
            "added": self.added,
            "dropped_final": self.dropped_final,
            "withdrawn": self.withdrawn,
            "inconsistent": self.inconsistent,
            "gate_sigmas": self.gate_sigmas,
            "agreed": self.agreed,
            "label": self.label,
            "trans_error": self.trans_error,
            "rot_error": self.rot_error,
        }


def closure_errors(
    pose: ArrayLike, reference_target: ArrayLike, reference_source: ArrayLike
) -> tuple[float, float]:
    """Translation (m) and rotation (rad) error of a proposed closure against the reference.

    Args:
        pose: Proposed pose of the source sensor frame in the target sensor frame.
        reference_target: Reference sensor pose of the target node (world).
        reference_source: Reference sensor pose of the source node (world).
    """
    truth = relative(as_pose(reference_target), as_pose(reference_source))
    err = relative(truth, as_pose(pose))
    return float(math.hypot(err[0], err[1])), float(abs(wrap_angle(err[2])))


def label_record(
    record: ClosureRecord, reference: NDArray[np.float64] | None, config: ClosureLabelConfig
) -> None:
    """Set ``record``'s errors and label from reference sensor poses that cover both scans."""
    c = record.candidate
    i, j = c.scan_index, c.target_scan_index
    if reference is None or max(i, j) >= len(reference):
        return
    record.trans_error, record.rot_error = closure_errors(c.pose, reference[j], reference[i])
    record.label = closure_label(record.trans_error, record.rot_error, config)


def closure_label(trans_error: float, rot_error: float, config: ClosureLabelConfig) -> int:
    """`NORMAL`, `FAULT` or `AMBIGUOUS` for a candidate's errors (see the module docstring)."""
    if not (math.isfinite(trans_error) and math.isfinite(rot_error)):
        return AMBIGUOUS
    rot_deg = math.degrees(rot_error)
    if trans_error > config.fault_translation or rot_deg > config.fault_rotation_deg:
        return FAULT
    if trans_error <= config.normal_translation and rot_deg <= config.normal_rotation_deg:
        return NORMAL
    return AMBIGUOUS


@runtime_checkable
class ClosureJudge(Protocol):
    """Decides whether a loop-closure candidate may enter the graph."""

    @property
    def name(self) -> str:
        """Short name (``none``, ``classical``, ``cnn``, ``oracle``)."""
        ...

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """The verdict on ``candidate``."""
        ...


class AcceptAll:
    """Accepts every candidate the search returns (no judging)."""

    name = "none"

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """Accept."""
        return ClosureVerdict(True, candidate.score, self.name)


@dataclass(frozen=True)
class AllOf:
    """Accepts a candidate only when every one of ``judges`` accepts it (asked in turn).

    The verdict's score is the first judge's; the name joins theirs with ``+``.
    """

    judges: tuple[ClosureJudge, ...]

    @property
    def name(self) -> str:
        """The judges' names joined with ``+``."""
        return "+".join(str(getattr(j, "name", type(j).__name__)) for j in self.judges)

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """The first refusal, else an acceptance with the first judge's score."""
        first: ClosureVerdict | None = None
        for judge in self.judges:
            verdict = judge(candidate)
            first = first or verdict
            if not verdict.accepted:
                return ClosureVerdict(False, first.score, self.name)
        assert first is not None
        return ClosureVerdict(True, first.score, self.name)


class ResponseTest:
    """Karto's classical closure test: enough response, small response-surface covariance.

    Args:
        min_response: Minimum fine response.
        max_std_xy: Maximum standard deviation in x and in y (m).
        max_std_theta: Maximum standard deviation in heading (rad).
    """

    name = "classical"

    def __init__(self, min_response: float, max_std_xy: float, max_std_theta: float) -> None:
        self.min_response = float(min_response)
        self.max_std_xy = float(max_std_xy)
        self.max_std_theta = float(max_std_theta)

    @classmethod
    def from_config(cls, config: ClosureJudgeConfig) -> ResponseTest:
        """The test with ``config``'s classical thresholds."""
        return cls(
            config.classical_min_response,
            config.classical_max_std_xy,
            config.classical_max_std_theta,
        )

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """Accept when the response and the standard deviations pass."""
        s = candidate.std
        ok = (
            candidate.score >= self.min_response
            and max(float(s[0]), float(s[1])) <= self.max_std_xy
            and float(s[2]) <= self.max_std_theta
        )
        return ClosureVerdict(bool(ok), candidate.score, self.name)


class DetectorClosureJudge:
    """The fault detector on a closure: current scan against the target node's scan.

    The pair is rendered at the proposed pose, as a sequential pair is rendered at its match.
    A detector that also reads ICP metrics gets those of the project's matcher (``matcher``,
    by default the one it was trained on) run on the pair from the proposed pose, so its
    inputs mean what they meant in training.

    Args:
        detector: A `scanguard.detect.detector.FaultDetector` (or anything with
            ``fault_probability(previous, current, pose, match)`` and ``threshold``).
        threshold: Fault-probability threshold (None = the detector's).
        matcher: Matcher for the ICP metrics (None = the detector's first training matcher,
            else ``icp-paper``).
    """

    name = "cnn"

    def __init__(self, detector: Any, threshold: float | None = None, matcher: Any = None) -> None:
        self.detector = detector
        self.threshold = float(detector.threshold if threshold is None else threshold)
        if matcher is None:
            trained = tuple(getattr(detector, "matchers", ()) or ())
            matcher = get_matcher(trained[0] if trained else "icp-paper")
        self.matcher = matcher
        self._needs_match = bool(getattr(detector, "metric_names", None))

    def probability(self, candidate: ClosureCandidate) -> float:
        """Fault probability of the candidate (NaN is returned as 1: a fault)."""
        match = None
        if self._needs_match:
            match = self.matcher(
                candidate.source.points(np.float64),
                candidate.target.points(np.float64),
                candidate.pose,
            )
        p = float(
            self.detector.fault_probability(
                candidate.target, candidate.source, candidate.pose, match=match
            )
        )
        return p if math.isfinite(p) else 1.0

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """Accept when the fault probability is below the threshold."""
        p = self.probability(candidate)
        return ClosureVerdict(p < self.threshold, p, self.name)


class ReferenceClosureJudge:
    """The oracle: accepts a candidate only when its reference label is normal.

    Args:
        reference_sensor: Reference sensor poses ``(N, 3)``, one per scan given to the back end.
        labels: Labelling thresholds.
    """

    name = "oracle"

    def __init__(self, reference_sensor: ArrayLike, labels: ClosureLabelConfig | None = None):
        self.reference = as_pose(reference_sensor).reshape(-1, 3)
        self.labels = labels or ClosureLabelConfig()

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """Accept when the candidate is within the normal limits of the reference."""
        i, j = candidate.scan_index, candidate.target_scan_index
        if max(i, j) >= len(self.reference):
            return ClosureVerdict(False, float("nan"), self.name)
        te, re = closure_errors(candidate.pose, self.reference[j], self.reference[i])
        return ClosureVerdict(closure_label(te, re, self.labels) == NORMAL, te, self.name)


__all__ = [
    "AMBIGUOUS",
    "FAULT",
    "NORMAL",
    "AcceptAll",
    "ClosureCandidate",
    "ClosureJudge",
    "ClosureJudgeConfig",
    "ClosureLabelConfig",
    "ClosureRecord",
    "ClosureVerdict",
    "DetectorClosureJudge",
    "ReferenceClosureJudge",
    "ResponseTest",
    "closure_errors",
    "closure_label",
]
