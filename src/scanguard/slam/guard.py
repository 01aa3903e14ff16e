"""The online loop of the paper's Figures 2 and 3, one scan at a time.

As each raw scan arrives it is matched to the previous raw scan, the pair is judged by the
fault detector (the CNN, a classical baseline, or both), and then:

* **accept** - the match increment moves the pose and the scan is inserted into the map;
* **reject** - the scan is discarded and the pose moves by the odometry increment for that
  step. Without odometry the pose either stays put (``constant_position``, default: the safest
  guess for a hand-held or slow sensor) or repeats the last applied increment
  (``constant_velocity``).

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

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from scanguard.config import YamlModel
from scanguard.errors import ConfigError, MatchingError
from scanguard.geometry import as_pose, compose, relative
from scanguard.pairs.features import pair_features
from scanguard.scan import LaserScan
from scanguard.slam.grid import (
    GridConfig,
    OccupancyGrid,
    robot_to_sensor_increment,
    sensor_to_robot_increment,
)
from scanguard.slam.metrics import centroid_distance_from_means

logger = logging.getLogger(__name__)

Points = NDArray[np.floating[Any]]
Policy = Literal["cnn", "baseline", "both", "none"]


@runtime_checkable
class MatchLike(Protocol):
    """What the loop needs from a match result (`scanguard.matching.MatchResult` fits)."""

    @property
    def pose(self) -> NDArray[np.float64]:
        """Estimated pose of the current sensor frame in the previous one."""
        ...


class Matcher(Protocol):
    """A scan matcher: ``matcher(source=current, target=previous, initial) -> match``."""

    def __call__(self, source: Points, target: Points, initial: Any = None) -> Any:
        """Match ``source`` onto ``target``; the result has a ``pose`` attribute."""
        ...


class Detector(Protocol):
    """Fault detector judged on the matched pair (`detect.detector.FaultDetector` fits)."""

    @property
    def threshold(self) -> float:
        """Probability at or above which a match is a fault."""
        ...

    def fault_probability(self, previous: LaserScan, current: LaserScan, pose: ArrayLike) -> float:
        """Probability that ``pose`` mis-aligns ``current`` onto ``previous``."""
        ...


class PairJudge(Protocol):
    """A classical (baseline) detector that may use the whole match result (its metrics)."""

    @property
    def name(self) -> str:
        """Short display name."""
        ...

    @property
    def threshold(self) -> float:
        """Score at or above which a match is a fault."""
        ...

    def score(self, previous: LaserScan, current: LaserScan, match: Any) -> float:
        """Fault score (probability-like, higher = more likely faulty)."""
        ...


def check_detector_matcher(detector: Any, matcher: Any, *, allow_other: bool = False) -> bool:
    """Check that ``detector`` was trained on the matches of ``matcher``.

    Only a detector that knows its matchers (``check_matcher``, as
    `scanguard.detect.detector.FaultDetector`) is checked. ``matcher`` is a registered name or a
    matcher object; an object without a ``name`` cannot be checked (logged as a warning).

    Args:
        detector: The CNN detector.
        matcher: Matcher name or object.
        allow_other: Accept a matcher the model was not trained for (logged as a warning).

    Returns:
        True when the detector was trained for the matcher (or cannot tell), False when it was
        not but ``allow_other`` is set.

    Raises:
        ModelError: The detector was not trained for the matcher and ``allow_other`` is off.
    """
    check = getattr(detector, "check_matcher", None)
    if not callable(check):
        return True
    name = matcher if isinstance(matcher, str) else getattr(matcher, "name", None)
    if not isinstance(name, str) or not name:
        logger.warning(
            "matcher %s has no name: cannot check that the model was trained on its matches",
            type(matcher).__name__,
        )
        return True
    return bool(check(name, allow_other=allow_other))


def _detector_features(detector: Any) -> list[str]:
    """Feature names a `scanguard.detect.baselines` detector reads."""
    if hasattr(detector, "feature"):
        return [str(detector.feature)]
    return [str(f) for f in (getattr(detector, "features", None) or [])]


class BaselineJudge:
    """A `scanguard.detect.baselines` detector (features -> fault score) as the loop's `PairJudge`.

    The features of a pair are exactly those the dataset stores for training
    (`scanguard.dataset.label_sequence`): the match's ``metrics()`` plus, when the detector
    reads a GMapping feature, `scanguard.matching.quality.gmapping_score` of the pair (the raw sum;
    ``gmapping_score_norm`` is derived by the detector as in training). The GMapping score is
    only computed when needed (it costs about as much as the ICP).

    Args:
        detector: A fitted `ThresholdDetector`, `MetricsModelDetector` or anything with
            ``name``, ``threshold`` and ``predict_proba(features)``.
        source: Where it came from (shown in reports).
    """

    def __init__(self, detector: Any, source: str = "<memory>") -> None:
        self.detector = detector
        self.source = source
        self.features = _detector_features(detector)
        self._needs_gmapping = any(f.startswith("gmapping") for f in self.features)

    @property
    def name(self) -> str:
        """The detector's display name."""
        return str(self.detector.name)

    @property
    def threshold(self) -> float:
        """Score at or above which a match is a fault (same decision as ``predict``)."""
        from scanguard.detect.baselines.threshold import ThresholdDetector

        if isinstance(self.detector, ThresholdDetector):
            # it flags strictly past its threshold, where predict_proba is exactly 0.5
            return float(np.nextafter(0.5, 1.0))
        return float(self.detector.threshold)

    def pair_features(self, previous: LaserScan, current: LaserScan, match: Any) -> dict[str, Any]:
        """Feature columns (length 1) of one matched pair."""
        return pair_features(previous, current, match, gmapping=self._needs_gmapping)

    def score(self, previous: LaserScan, current: LaserScan, match: Any) -> float:
        """Fault score of the detector for one matched pair (higher = more likely a fault)."""
        feats = self.pair_features(previous, current, match)
        return float(self.detector.predict_proba(feats)[0])

    def __repr__(self) -> str:
        return f"BaselineJudge({self.detector!r}, source={self.source!r})"


class GuardConfig(YamlModel):
    """Settings of the online loop.

    Attributes:
        policy: Who decides: ``cnn``, ``baseline``, ``both`` (a match is accepted only if neither
            flags it) or ``none`` (plain ICP chaining: accept every usable match).
        cnn_threshold: Fault threshold of the CNN (None = the detector's own).
        baseline_threshold: Fault threshold of the baseline (None = the judge's own).
        odometry_initial_guess: Seed the matcher with the odometry increment. Off by default:
            the paper starts ICP from the identity.
        fallback: Motion on reject when no odometry is given (see module docstring).
        min_points: A scan with fewer valid points cannot be matched.
        score_all: Also compute the probability of the detector(s) the policy does not use
            (for side-by-side comparisons in one pass).
        update_map: Keep an occupancy grid of accepted scans.
        map_in_background: Insert accepted scans into the grid on a worker thread of this guard
            (the numba ray tracer releases the GIL), so the map update leaves the per-scan
            critical path, as in SLAM systems that map in a separate thread. The grid is the
            same (inserts keep their order); reading `ScanGuard.grid` waits for pending ones.
        grid: Occupancy grid settings.
    """

    policy: Policy = "cnn"
    cnn_threshold: float | None = Field(default=None, ge=0.0, le=1.0)
    baseline_threshold: float | None = Field(default=None, allow_inf_nan=False)
    odometry_initial_guess: bool = False
    fallback: Literal["constant_position", "constant_velocity"] = "constant_position"
    min_points: int = Field(default=10, ge=3)
    score_all: bool = False
    update_map: bool = True
    map_in_background: bool = False
    grid: GridConfig = Field(default_factory=lambda: GridConfig())


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
            ``map`` (only the hand-over to the worker with ``map_in_background``) and
            ``total``.
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


_NAN3 = np.full(3, np.nan)


def _timed_insert(grid: OccupancyGrid, scan: LaserScan, laser_pose: NDArray[np.float64]) -> float:
    t = time.perf_counter()
    grid.insert(scan, laser_pose)
    return time.perf_counter() - t


class ScanGuard:
    """Streaming scan-matching fault guard with a fused pose and an occupancy grid.

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
        self.config = config or GuardConfig()
        self.detector = detector
        self.matcher = matcher
        self.baseline = baseline
        pol = self.config.policy
        if pol in ("cnn", "both") and detector is None:
            raise ConfigError(f"policy {pol!r} needs a CNN detector, none was given")
        if pol in ("baseline", "both") and baseline is None:
            raise ConfigError(f"policy {pol!r} needs a baseline detector, none was given")
        # a NaN threshold would pass every match (NaN comparisons are false): refuse it
        if detector is not None and not 0.0 <= self.cnn_threshold <= 1.0:
            raise ConfigError(
                f"CNN threshold {self.cnn_threshold} is not a probability in [0, 1] "
                f"(detector {getattr(detector, 'source', type(detector).__name__)})"
            )
        if baseline is not None and not math.isfinite(self.baseline_threshold):
            raise ConfigError(f"baseline threshold {self.baseline_threshold} is not finite")
        if detector is not None:
            check_detector_matcher(detector, matcher, allow_other=allow_other_matcher)
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self._initial_pose = as_pose(initial_pose).reshape(3).copy()
        self._grid: OccupancyGrid | None = None
        self._map_worker: ThreadPoolExecutor | None = None
        self._map_jobs: list[Future[float]] = []
        #: Seconds spent by each background map insert (``map_in_background`` only).
        self.background_map_seconds: list[float] = []
        self._warned_non_finite: set[str] = set()
        self.reset()

    @property
    def grid(self) -> OccupancyGrid | None:
        """The occupancy grid of accepted scans (None if ``update_map`` is off); up to date."""
        self.flush()
        return self._grid

    def flush(self) -> None:
        """Wait for pending background map inserts (re-raising their errors)."""
        jobs, self._map_jobs = self._map_jobs, []
        for job in jobs:
            self.background_map_seconds.append(job.result())

    def close(self) -> None:
        """Finish pending map inserts and stop the map worker thread (if any)."""
        self.flush()
        if self._map_worker is not None:
            self._map_worker.shutdown(wait=True)
            self._map_worker = None

    def __enter__(self) -> ScanGuard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def reset(self, initial_pose: ArrayLike | None = None) -> None:
        """Forget all state (pose, previous scan, map, counters)."""
        self.flush()
        self.background_map_seconds = []
        if initial_pose is not None:
            self._initial_pose = as_pose(initial_pose).reshape(3).copy()
        self.pose = self._initial_pose.copy()
        self._prev_points: Points | None = None
        self._prev_mean: NDArray[np.float64] = np.full(2, np.nan)
        self._prev_scan: LaserScan | None = None
        self._prev_odom: NDArray[np.float64] | None = None
        self._last_increment = np.zeros(3)
        self.index = 0
        self.n_accepted = 0
        self.n_rejected = 0
        self.n_failed = 0
        self.n_skipped = 0
        #: Judgements whose probability or score was not finite (each counted as a fault).
        self.n_non_finite = 0
        self._grid = None
        if self.config.update_map:
            p0 = self.pose
            self._grid = OccupancyGrid(
                self.config.grid, origin=(float(p0[0]) - 10.0, float(p0[1]) - 10.0)
            )

    @property
    def cnn_threshold(self) -> float:
        """Effective CNN threshold."""
        if self.config.cnn_threshold is not None:
            return float(self.config.cnn_threshold)
        return float(self.detector.threshold) if self.detector is not None else 0.5

    @property
    def baseline_threshold(self) -> float:
        """Effective baseline threshold."""
        if self.config.baseline_threshold is not None:
            return float(self.config.baseline_threshold)
        return float(self.baseline.threshold) if self.baseline is not None else 0.5

    def _insert(self, scan: LaserScan) -> float:
        grid = self._grid
        if grid is None:
            return 0.0
        t = time.perf_counter()
        laser_pose = compose(self.pose, self.laser_offset)
        if self.config.map_in_background:
            if self._map_worker is None:
                self._map_worker = ThreadPoolExecutor(1, thread_name_prefix="scanguard-map")
            self._map_jobs.append(self._map_worker.submit(_timed_insert, grid, scan, laser_pose))
        else:
            grid.insert(scan, laser_pose)
        return time.perf_counter() - t

    def _fallback_increment(self, odom_inc: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """Increment applied without a usable match: odometry, else the configured fallback."""
        if odom_inc is not None:
            return odom_inc
        if self.config.fallback == "constant_velocity":
            return self._last_increment.copy()
        return np.zeros(3)

    def _fault_probability(
        self,
        prev_scan: LaserScan,
        scan: LaserScan,
        previous: Points,
        points: Points,
        pose: NDArray[np.float64],
        match: Any = None,
        odometry: NDArray[np.float64] | None = None,
    ) -> float:
        det: Any = self.detector
        style = getattr(det, "style", None)
        if style is not None and callable(getattr(det, "predict_images", None)):
            # `FaultDetector`: render the points already computed for the matcher (the very
            # arrays its own `render` would compute from the scans, so the image is identical)
            from scanguard.detect.render import render_pair

            image = render_pair(previous, points, pose, style)
            if getattr(det, "metric_names", None):  # hybrid model: also reads the ICP metrics
                if getattr(det, "reads_odometry", False):
                    feats = det.match_features(previous, points, match, odometry)
                else:
                    feats = det.match_features(previous, points, match)
                return float(det.predict_images(image[None], features=feats)[0])
            return float(det.predict_images(image[None])[0])
        return float(det.fault_probability(prev_scan, scan, pose))

    def _is_fault(self, value: float, threshold: float, who: str, index: int) -> bool:
        """``value >= threshold``, and True for a non-finite value (fail-safe, warned once)."""
        if math.isfinite(value):
            return value >= threshold
        self.n_non_finite += 1
        if who not in self._warned_non_finite:
            self._warned_non_finite.add(who)
            logger.warning(
                "scan %d: the %s's fault %s is %s; treating the match as a fault (reported "
                "once per guard; see n_non_finite)",
                index,
                who,
                "probability" if who == "CNN" else "score",
                value,
            )
        return True

    def _unmatched(
        self,
        index: int,
        scan: LaserScan,
        reason: str,
        odometry_increment: NDArray[np.float64] | None,
        applied: NDArray[np.float64],
        timings: dict[str, float],
    ) -> Decision:
        """The decision of a step without a match: the first scan (accepted) or a skipped one."""
        return Decision(
            index=index,
            stamp=scan.stamp,
            accepted=reason == "first",
            reason=reason,
            match=None,
            fault_probability=float("nan"),
            baseline_score=float("nan"),
            match_increment=_NAN3.copy(),
            odometry_increment=odometry_increment,
            applied_increment=applied,
            pose=self.pose.copy(),
            timings=timings,
        )

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
                the fallback) and the decision has reason ``"skipped"`` (not accepted, NaN
                scores). The first scan is never judged, so ``judge`` does not change it.

        Returns:
            The decision for this scan.
        """
        t_start = time.perf_counter()
        timings = {"match": 0.0, "detect": 0.0, "baseline": 0.0, "map": 0.0}
        points = scan.points()
        # the centroid of each scan is needed twice (as current, then as previous scan)
        mean = points.mean(axis=0, dtype=np.float64) if len(points) else np.full(2, np.nan)
        odom = None if odometry is None else as_pose(odometry).reshape(3).copy()
        index = self.index
        self.index += 1

        if (self._prev_points is not None and self._prev_scan is not None) and not judge:
            skip_inc: NDArray[np.float64] | None = None
            if odom is not None and self._prev_odom is not None:
                skip_inc = relative(self._prev_odom, odom)
            skip_applied = self._fallback_increment(skip_inc)
            self.pose = compose(self.pose, skip_applied)
            self._last_increment = skip_applied.copy()
            self.n_skipped += 1
            self._prev_points, self._prev_scan, self._prev_odom = points, scan, odom
            self._prev_mean = mean
            timings["total"] = time.perf_counter() - t_start
            return self._unmatched(index, scan, "skipped", skip_inc, skip_applied, timings)

        if self._prev_points is None or self._prev_scan is None:
            self._prev_points, self._prev_scan, self._prev_odom = points, scan, odom
            self._prev_mean = mean
            timings["map"] = self._insert(scan)
            self.n_accepted += 1
            timings["total"] = time.perf_counter() - t_start
            return self._unmatched(index, scan, "first", None, np.zeros(3), timings)

        previous = self._prev_points
        prev_scan = self._prev_scan
        odom_inc: NDArray[np.float64] | None = None
        if odom is not None and self._prev_odom is not None:
            odom_inc = relative(self._prev_odom, odom)
        initial = None
        if self.config.odometry_initial_guess and odom_inc is not None:
            initial = robot_to_sensor_increment(odom_inc, self.laser_offset)

        match: Any = None
        t = time.perf_counter()
        if len(points) >= self.config.min_points and len(previous) >= self.config.min_points:
            try:
                match = self.matcher(points, previous, initial)
            except MatchingError as exc:
                logger.debug("scan %d: matcher failed: %s", index, exc)
            if match is not None and not (
                np.all(np.isfinite(np.asarray(match.pose))) and getattr(match, "ok", True)
            ):
                match = None
        timings["match"] = time.perf_counter() - t

        pol = self.config.policy
        p_cnn = float("nan")
        s_base = float("nan")
        cnn_fault = base_fault = False
        if match is not None:
            est = np.asarray(match.pose, dtype=np.float64)
            if self.detector is not None and (pol in ("cnn", "both") or self.config.score_all):
                t = time.perf_counter()
                odo_sensor = (
                    None
                    if odom_inc is None
                    else robot_to_sensor_increment(odom_inc, self.laser_offset)
                )
                p_cnn = self._fault_probability(
                    prev_scan, scan, previous, points, est, match, odo_sensor
                )
                timings["detect"] = time.perf_counter() - t
                cnn_fault = self._is_fault(p_cnn, self.cnn_threshold, "CNN", index)
            if self.baseline is not None and (pol in ("baseline", "both") or self.config.score_all):
                t = time.perf_counter()
                s_base = float(self.baseline.score(prev_scan, scan, match))
                timings["baseline"] = time.perf_counter() - t
                base_fault = self._is_fault(s_base, self.baseline_threshold, "baseline", index)

        if match is None:
            accepted, reason = False, "match_failed"
        else:
            flag_cnn = cnn_fault and pol in ("cnn", "both")
            flag_base = base_fault and pol in ("baseline", "both")
            accepted = not (flag_cnn or flag_base)
            if accepted:
                reason = "accepted"
            elif flag_cnn and flag_base:
                reason = "rejected_both"
            else:
                reason = "rejected_cnn" if flag_cnn else "rejected_baseline"

        match_inc = (
            _NAN3.copy()
            if match is None
            else sensor_to_robot_increment(
                np.asarray(match.pose, dtype=np.float64), self.laser_offset
            )
        )
        applied = match_inc if accepted else self._fallback_increment(odom_inc)
        self.pose = compose(self.pose, applied)
        self._last_increment = applied.copy()
        if accepted:
            self.n_accepted += 1
            timings["map"] = self._insert(scan)
        else:
            self.n_rejected += 1
            if match is None:
                self.n_failed += 1

        c_match = float("nan")
        if match is not None:
            c_match = centroid_distance_from_means(
                self._prev_mean, mean, np.asarray(match.pose, dtype=np.float64)
            )
        c_applied = centroid_distance_from_means(
            self._prev_mean, mean, robot_to_sensor_increment(applied, self.laser_offset)
        )
        self._prev_points, self._prev_scan, self._prev_odom = points, scan, odom
        self._prev_mean = mean
        timings["total"] = time.perf_counter() - t_start
        return Decision(
            index=index,
            stamp=scan.stamp,
            accepted=accepted,
            reason=reason,
            match=match,
            fault_probability=p_cnn,
            baseline_score=s_base,
            match_increment=match_inc,
            odometry_increment=odom_inc,
            applied_increment=np.asarray(applied, dtype=np.float64),
            pose=self.pose.copy(),
            centroid_match=c_match,
            centroid_applied=c_applied,
            timings=timings,
        )
