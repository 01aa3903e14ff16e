"""The online loop of the paper's Figures 2 and 3, one scan at a time.

As each raw scan arrives it is matched to the previous raw scan (`ScanPairs`), the pair is
judged (`scanguard.slam.judge.Judge`: the CNN, a classical baseline, or both), the guard's
`scanguard.slam.gate.Gate` turns the verdict into a decision, and the ``frontend`` back end
(`scanguard.slam.backend.FrontendBackend`) chains the poses and keeps the map:

* **accept** - the match increment moves the pose and the scan is inserted into the map;
* **reject** - the scan is discarded and the pose moves by the odometry increment for that
  step. Without odometry the pose follows the motion prior: it stays put
  (``constant_position``, default: the safest guess for a hand-held or slow sensor) or repeats
  the last applied increment (``constant_velocity``).

A step whose match is unusable (too few points, matcher error, non-finite estimate) is handled
like a reject, with reason ``"match_failed"``. A fault probability or baseline score that is
not finite (a broken model outputs NaN) counts as a fault: fail-safe, the scan is rejected and
the guard logs a warning the first time. A step the caller does not want judged
(``step(..., judge=False)``: no back end would use the scan) skips the matcher and detectors
and is handled like a reject too, with reason ``"skipped"``; the scan still becomes the
previous scan of the next pair.

`ScanGuard` holds all state itself (no module globals), so several guards can run side by side.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import AliasChoices, Field

from scanguard.config import YamlModel
from scanguard.errors import ConfigError
from scanguard.geometry import as_pose, relative
from scanguard.matching.registry import Matcher
from scanguard.scan import LaserScan
from scanguard.slam.backend import FrontendBackend, MotionPrior
from scanguard.slam.gate import Gate, NonFiniteWatch
from scanguard.slam.grid import GridConfig, robot_to_sensor_increment, sensor_to_robot_increment
from scanguard.slam.judge import Detector, Judge, PairJudge, Verdict, check_detector_matcher
from scanguard.slam.metrics import centroid_distance_from_means
from scanguard.slam.pair import Frame, match_frames

Policy = Literal["cnn", "baseline", "both", "none"]
_NAN3 = np.full(3, np.nan)


class GuardConfig(YamlModel):
    """Settings of the online loop.

    Attributes:
        policy: Who decides: ``cnn``, ``baseline``, ``both`` (a match is accepted only if neither
            flags it) or ``none`` (plain ICP chaining: accept every usable match).
        cnn_threshold: Fault threshold of the CNN (None = the detector's own).
        baseline_threshold: Fault threshold of the baseline (None = the judge's own).
        odometry_initial_guess: Seed the matcher with the odometry increment. Off by default:
            the paper starts ICP from the identity.
        motion_prior: Motion on reject when no odometry is given (see module docstring); the
            YAML key ``fallback`` is read as an alias.
        min_points: A scan with fewer valid points cannot be matched.
        score_all: Also compute the probability of the detector(s) the policy does not use
            (for side-by-side comparisons in one pass).
        update_map: Keep an occupancy grid of accepted scans.
        map_in_background: Insert accepted scans into the grid on a worker thread of this guard
            (the numba ray tracer releases the GIL), so the map update leaves the per-scan
            critical path, as in SLAM systems that map in a separate thread. The grid is the
            same (inserts keep their order); reading `ScanGuard.grid` waits for pending ones.
        grid: Occupancy grid settings.
        judge_with_odometry: Hand the odometry disagreement to the detector (False: it judges
            the match's geometry alone, the odometry input masked). None (default): False
            where the fused motion model tests the wheels against the match itself
            (``motion: fused``), True elsewhere (the paper's loop, the streaming guard).
        odometry_below_eig: With ``judge_with_odometry`` False, the judge still reads the
            odometry for degenerate matches (``eig_min_per_inlier`` below this; None: never).
        fit_odometry_noise: Before the run, fit this robot's odometry noise from its own
            matches (`scanguard.apps.self_calibration`) so that a detector that reads the
            odometry disagreement reads it in this robot's units (no reference needed).
    """

    policy: Policy = "cnn"
    cnn_threshold: float | None = Field(default=None, ge=0.0, le=1.0)
    baseline_threshold: float | None = Field(default=None, allow_inf_nan=False)
    odometry_initial_guess: bool = False
    motion_prior: MotionPrior = Field(
        default="constant_position",
        validation_alias=AliasChoices("motion_prior", "fallback"),
    )
    min_points: int = Field(default=10, ge=3)
    score_all: bool = False
    update_map: bool = True
    map_in_background: bool = False
    grid: GridConfig = Field(default_factory=lambda: GridConfig())
    fit_odometry_noise: bool = False
    judge_with_odometry: bool | None = None
    odometry_below_eig: float | None = Field(default=None, gt=0.0)


def cnn_threshold(config: GuardConfig, detector: Any) -> float:
    """Effective CNN threshold: the configured one, else the detector's (0.5 without one)."""
    if config.cnn_threshold is not None:
        return float(config.cnn_threshold)
    return float(detector.threshold) if detector is not None else 0.5


def baseline_threshold(config: GuardConfig, baseline: Any) -> float:
    """Effective baseline threshold: the configured one, else the judge's (0.5 without one)."""
    if config.baseline_threshold is not None:
        return float(config.baseline_threshold)
    return float(baseline.threshold) if baseline is not None else 0.5


def policy_gate(config: GuardConfig, detector: Any, baseline: Any) -> Gate:
    """The gate of the configured policy, with the effective thresholds.

    Raises:
        ConfigError: The policy needs a detector that was not given, or a detector's threshold
            is NaN (or, for the CNN, outside [0, 1]).
    """
    pol = config.policy
    if pol in ("cnn", "both") and detector is None:
        raise ConfigError(f"policy {pol!r} needs a CNN detector, none was given")
    if pol in ("baseline", "both") and baseline is None:
        raise ConfigError(f"policy {pol!r} needs a baseline detector, none was given")
    t_cnn, t_base = cnn_threshold(config, detector), baseline_threshold(config, baseline)
    # a NaN threshold would pass every match (NaN comparisons are false): refuse it
    if detector is not None and not 0.0 <= t_cnn <= 1.0:
        raise ConfigError(
            f"CNN threshold {t_cnn} is not a probability in [0, 1] "
            f"(detector {getattr(detector, 'source', type(detector).__name__)})"
        )
    if baseline is not None and not math.isfinite(t_base):
        raise ConfigError(f"baseline threshold {t_base} is not finite")
    return Gate(pol, cnn_threshold=t_cnn, baseline_threshold=t_base)


@dataclass
class JudgedPair:
    """One scan and, unless it is the first or skipped, its match to the previous one judged.

    Attributes:
        index: Scan counter (0 = first scan).
        current: The scan.
        previous: The previous scan (None for the first).
        judged: Matched and judged (False: the first scan, or a scan the caller skipped).
        match: The matcher's result (None: not judged, or the match failed).
        verdict: The judge's verdict (None without a match).
        odometry_increment: Robot-frame odometry increment since the previous scan, or None.
        match_increment: Robot-frame increment of the match (NaN without one).
        centroid_match: Paper Fig. 19 error of the match (m, NaN without one).
        timings: Seconds of ``match``, ``detect`` (render + CNN) and ``baseline``.
    """

    index: int
    current: Frame
    previous: Frame | None
    judged: bool
    match: Any = None
    verdict: Verdict | None = None
    odometry_increment: NDArray[np.float64] | None = None
    match_increment: NDArray[np.float64] = field(default_factory=lambda: _NAN3.copy())
    centroid_match: float = float("nan")
    timings: dict[str, float] = field(
        default_factory=lambda: {"match": 0.0, "detect": 0.0, "baseline": 0.0}
    )

    @property
    def match_pose(self) -> NDArray[np.float64] | None:
        """Sensor-frame pose of the match (None without one)."""
        return None if self.match is None else np.asarray(self.match.pose, dtype=np.float64)

    def reason(self, decided: str) -> str:
        """``first``, ``skipped``, ``match_failed``, else the gate's reason ``decided``."""
        if self.previous is None:
            return "first"
        if not self.judged:
            return "skipped"
        return "match_failed" if self.match is None else decided


class ScanPairs:
    """Consecutive scans, each matched to the previous one and judged (the guard's front half).

    Args:
        matcher: Scan matcher; called as ``matcher(current_points, previous_points, initial)``.
        judge: The judge of a matched pair.
        min_points: A scan with fewer valid points cannot be matched.
        odometry_initial_guess: Seed the matcher with the odometry increment.
        laser_offset: Pose of the laser in the robot frame.
    """

    def __init__(
        self,
        matcher: Matcher | Callable[..., Any],
        judge: Judge,
        *,
        min_points: int = 10,
        odometry_initial_guess: bool = False,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        self.matcher = matcher
        self.judge = judge
        self.min_points = min_points
        self.odometry_initial_guess = odometry_initial_guess
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self.index = 0
        self._previous: Frame | None = None

    def step(
        self,
        scan: LaserScan,
        odometry: ArrayLike | None = None,
        judge: bool = True,
        guess: ArrayLike | None = None,
    ) -> JudgedPair:
        """The next scan (``odometry``: absolute pose or None), matched and judged if ``judge``.

        ``guess``: a robot-frame increment that seeds the matcher (the fused motion's
        prediction), in place of the odometry seed of ``odometry_initial_guess``.
        """
        current = Frame.of(scan, odometry)
        previous, self._previous = self._previous, current
        pair = JudgedPair(self.index, current, previous, judged=previous is not None and judge)
        self.index += 1
        if previous is None:
            return pair
        if current.odometry is not None and previous.odometry is not None:
            pair.odometry_increment = relative(previous.odometry, current.odometry)
        if pair.judged:
            self._match_and_judge(pair, previous, guess)
        return pair

    def _match_and_judge(
        self, pair: JudgedPair, previous: Frame, guess: ArrayLike | None = None
    ) -> None:
        initial = None
        if guess is not None:
            initial = robot_to_sensor_increment(as_pose(guess).reshape(3), self.laser_offset)
        elif self.odometry_initial_guess and pair.odometry_increment is not None:
            initial = robot_to_sensor_increment(pair.odometry_increment, self.laser_offset)
        t = time.perf_counter()
        pair.match = match_frames(
            self.matcher,
            previous,
            pair.current,
            min_points=self.min_points,
            initial=initial,
            index=pair.index,
        )
        pair.timings["match"] = time.perf_counter() - t
        pose = pair.match_pose
        if pose is None:
            return
        pair.match_increment = sensor_to_robot_increment(pose, self.laser_offset)
        pair.centroid_match = centroid_distance_from_means(previous.mean, pair.current.mean, pose)
        pair.verdict = v = self.judge(previous, pair.current, pair.match, pair.odometry_increment)
        pair.timings["detect"], pair.timings["baseline"] = v.detect_seconds, v.baseline_seconds


@dataclass
class Decision:
    """Outcome of one `ScanGuard.step`.

    Attributes:
        index: Scan counter (0 = first scan).
        stamp: Scan stamp (s).
        accepted: The match was used (always True for the first scan).
        reason: ``first``, ``accepted``, ``rejected_cnn``, ``rejected_baseline``,
            ``rejected_both``, ``match_failed`` or ``skipped`` (not judged, see
            `ScanGuard.step`).
        match: The matcher's result, or None (first scan / failure).
        fault_probability: CNN fault probability (NaN when not computed).
        baseline_score: Baseline fault score (NaN when not computed).
        match_increment: Robot-frame increment from the match (NaN if none).
        odometry_increment: Robot-frame odometry increment, or None without odometry.
        applied_increment: Robot-frame increment actually applied to the pose.
        pose: Fused robot pose after this step.
        centroid_match: Paper Fig. 19 error of the raw match (m, NaN if none).
        centroid_applied: Paper Fig. 19 error of the applied increment (m, NaN if none).
        timings: Seconds per stage: ``match``, ``detect`` (render + CNN), ``baseline``,
            ``map`` (the back end's update; only the hand-over to the worker with
            ``map_in_background``) and ``total``.
    """

    index: int
    stamp: float
    accepted: bool
    reason: str
    match: Any
    fault_probability: float
    baseline_score: float
    match_increment: NDArray[np.float64]
    odometry_increment: NDArray[np.float64] | None
    applied_increment: NDArray[np.float64]
    pose: NDArray[np.float64]
    centroid_match: float = float("nan")
    centroid_applied: float = float("nan")
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def cnn_fault(self) -> bool:
        """True when the reason names the CNN."""
        return self.reason in ("rejected_cnn", "rejected_both")


@dataclass
class GuardCounts:
    """Scans by outcome (the first scan counts as accepted; failed matches as rejected)."""

    accepted: int = 0
    rejected: int = 0
    failed: int = 0
    skipped: int = 0

    def add(self, reason: str) -> None:
        """Count one step's reason."""
        if reason == "skipped":
            self.skipped += 1
        elif reason in ("first", "accepted"):
            self.accepted += 1
        else:
            self.rejected += 1
            self.failed += reason == "match_failed"


class ScanGuard:
    """Streaming scan-matching fault guard: pairs -> judge -> gate -> the ``frontend`` back end.

    Args:
        detector: The CNN detector (required by policies ``cnn`` and ``both``).
        matcher: Scan matcher; called as ``matcher(current_points, previous_points, initial)``.
        config: Loop settings (defaults if None).
        baseline: Classical detector (required by policies ``baseline`` and ``both``).
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose assigned to the first scan.
        allow_other_matcher: Accept a CNN detector trained on another matcher's matches
            (`check_detector_matcher`; its verdicts are then uncalibrated).

    Raises:
        ConfigError: The policy needs a detector that was not given, or a detector's
            threshold is NaN (or, for the CNN, outside [0, 1]).
        ModelError: The CNN detector was not trained on ``matcher``'s matches and
            ``allow_other_matcher`` is off.
    """

    def __init__(
        self,
        detector: Detector | None,
        matcher: Matcher | Callable[..., Any],
        config: GuardConfig | None = None,
        *,
        baseline: PairJudge | None = None,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
        initial_pose: ArrayLike = (0.0, 0.0, 0.0),
        allow_other_matcher: bool = False,
    ) -> None:
        self.config = cfg = config or GuardConfig()
        self.detector = detector
        self.matcher = matcher
        self.baseline = baseline
        self.gate = policy_gate(cfg, detector, baseline)
        if detector is not None:
            check_detector_matcher(detector, matcher, allow_other=allow_other_matcher)
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self._initial_pose = as_pose(initial_pose).reshape(3).copy()
        # only the detectors the policy reads are asked (all of them with ``score_all``)
        use_cnn = cfg.policy in ("cnn", "both") or cfg.score_all
        use_base = cfg.policy in ("baseline", "both") or cfg.score_all
        self.judge = Judge(
            detector if use_cnn else None,
            baseline if use_base else None,
            laser_offset=self.laser_offset,
        )
        self.frontend: FrontendBackend | None = None
        self.watch = NonFiniteWatch()
        self.reset()

    @property
    def cnn_threshold(self) -> float:
        """Effective CNN threshold."""
        return self.gate.cnn_threshold

    @property
    def baseline_threshold(self) -> float:
        """Effective baseline threshold."""
        return self.gate.baseline_threshold

    @property
    def pose(self) -> NDArray[np.float64]:
        """Current fused robot pose."""
        return self._frontend.pose

    @property
    def grid(self) -> Any:
        """The occupancy grid of accepted scans (None if ``update_map`` is off); up to date."""
        return self._frontend.grid()

    @property
    def background_map_seconds(self) -> list[float]:
        """Seconds spent by each background map insert (``map_in_background`` only)."""
        return self._frontend.background_map_seconds

    @property
    def n_accepted(self) -> int:
        """Accepted scans (the first included)."""
        return self.counts.accepted

    @property
    def n_rejected(self) -> int:
        """Rejected scans (failed matches included)."""
        return self.counts.rejected

    @property
    def n_failed(self) -> int:
        """Scans whose match failed."""
        return self.counts.failed

    @property
    def n_skipped(self) -> int:
        """Scans not judged (``step(..., judge=False)``)."""
        return self.counts.skipped

    @property
    def n_non_finite(self) -> int:
        """Judgements whose probability or score was not finite (each counted as a fault)."""
        return self.watch.count

    @property
    def _frontend(self) -> FrontendBackend:
        assert self.frontend is not None  # set by reset()
        return self.frontend

    def flush(self) -> None:
        """Wait for pending background map inserts (re-raising their errors)."""
        self._frontend.flush()

    def close(self) -> None:
        """Finish pending map inserts and stop the map worker thread (if any)."""
        self._frontend.close()

    def __enter__(self) -> ScanGuard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def reset(self, initial_pose: ArrayLike | None = None) -> None:
        """Forget all state (pose, previous scan, map, counters)."""
        if self.frontend is not None:
            self.frontend.close()
        if initial_pose is not None:
            self._initial_pose = as_pose(initial_pose).reshape(3).copy()
        cfg = self.config
        self.frontend = FrontendBackend(
            laser_offset=self.laser_offset,
            initial_pose=self._initial_pose,
            motion_prior=cfg.motion_prior,
            grid=cfg.grid,
            update_map=cfg.update_map,
            map_in_background=cfg.map_in_background,
        )
        self.pairs = ScanPairs(
            self.matcher,
            self.judge,
            min_points=cfg.min_points,
            odometry_initial_guess=cfg.odometry_initial_guess,
            laser_offset=self.laser_offset,
        )
        self.counts = GuardCounts()
        # the count restarts, but each detector's non-finite output is warned about once per guard
        self.watch = NonFiniteWatch(warned=self.watch.warned)

    @property
    def index(self) -> int:
        """Scans seen since the last reset."""
        return self.pairs.index

    def step(
        self, scan: LaserScan, odometry: ArrayLike | None = None, judge: bool = True
    ) -> Decision:
        """Process one scan.

        Args:
            scan: The new raw scan.
            odometry: Absolute odometry pose ``(x, y, theta)`` of the robot at ``scan.stamp``
                (only increments between consecutive calls are used), or None.
            judge: Match and judge the pair. False skips the (expensive) matcher and
                detectors, for a scan no back end wants: the scan only becomes the previous
                scan of the next step, the pose moves as on a reject (odometry increment, else
                the motion prior) and the decision has reason ``"skipped"`` (not accepted, NaN
                scores). The first scan is never judged, so ``judge`` does not change it.

        Returns:
            The decision for this scan.
        """
        t_start = time.perf_counter()
        pair = self.pairs.step(scan, odometry, judge=judge)
        self.watch(pair.verdict, pair.index)
        decided = self.gate.decide(pair.verdict)
        first = pair.previous is None
        accepted = first or decided.accepted
        reason = pair.reason(decided.reason)
        self.counts.add(reason)
        fe = self._frontend
        t = time.perf_counter()
        fe.update(scan, pair.current.odometry, usable=accepted, match=pair.match_pose)
        timings = {**pair.timings, "map": time.perf_counter() - t}
        timings["total"] = time.perf_counter() - t_start
        return self._decision(pair, accepted, reason, timings)

    def _decision(
        self, pair: JudgedPair, accepted: bool, reason: str, timings: dict[str, float]
    ) -> Decision:
        fe = self._frontend
        applied = fe.increment.copy()
        c_applied = float("nan")
        if pair.judged and pair.previous is not None:
            c_applied = centroid_distance_from_means(
                pair.previous.mean,
                pair.current.mean,
                robot_to_sensor_increment(applied, self.laser_offset),
            )
        verdict = pair.verdict or Verdict()
        return Decision(
            index=pair.index,
            stamp=pair.current.scan.stamp,
            accepted=accepted,
            reason=reason,
            match=pair.match,
            fault_probability=verdict.probability,
            baseline_score=verdict.score,
            match_increment=pair.match_increment,
            odometry_increment=pair.odometry_increment,
            applied_increment=applied,
            pose=fe.pose,
            centroid_match=pair.centroid_match,
            centroid_applied=c_applied,
            timings=timings,
        )
