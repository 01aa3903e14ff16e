"""The guard's front half: each raw scan matched to the previous one and judged.

`ScanPairs` matches each new scan to the previous raw scan and has the pair judged
(`scanguard.slam.judge.Judge`: the CNN, a classical baseline, or both); `GuardConfig` holds
the guard's settings (its policy, thresholds, motion prior, map); `policy_gate` builds the one
`scanguard.slam.gate.Gate` of the policy. A match that is unusable (too few points, matcher
error, non-finite estimate) gives a pair without a verdict (reason ``"match_failed"``); a pair
the caller does not want judged is ``"skipped"``. What a decision does to the robot's motion
and map is the per-scan step's (`scanguard.slam.loop.RunLoop`), for a whole run, the ROS node
and the streaming `scanguard.slam.stream.ScanGuard` alike.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import AliasChoices, Field

from scanguard.config import YamlModel
from scanguard.detect.adaptive import AdaptiveConfig, OperatingPoint, with_operating_point
from scanguard.errors import ConfigError
from scanguard.geometry import as_pose, compose, relative
from scanguard.matching.registry import Matcher
from scanguard.scan import LaserScan
from scanguard.slam.backend import MotionPrior
from scanguard.slam.free_space import FreeSpaceHistory, chain
from scanguard.slam.gate import Gate
from scanguard.slam.grid import GridConfig, robot_to_sensor_increment, sensor_to_robot_increment
from scanguard.slam.judge import Judge, Verdict
from scanguard.slam.metrics import centroid_distance_from_means
from scanguard.slam.pair import Frame, match_frames
from scanguard.slam.wheel_support import WheelSupport

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
        wheel_support: Reject a pair whose scan supports the wheels over the last five
            matches (`scanguard.slam.wheel_support`: a person keeping pace ahead), where the
            robot has odometry. None (default): on with the ``graph`` back end (session 27,
            README "The wheel-support test, the default"), off with the others (GMapping,
            measured: ACES +6 %) and in the streaming `ScanGuard`.
        wheel_support_remedy: What reaches the back end of a pair the wheel-support test
            rejects: ``drop``, nothing (its node holds by the fused step); ``mask``, the scan
            without the beams whose points supported the matches (what they followed).
        fit_odometry_noise: Before the run, fit this robot's odometry noise from its own
            matches (`scanguard.apps.self_calibration`) so that a detector that reads the
            odometry disagreement reads it in this robot's units (no reference needed).
        free_space_horizon: Seconds of recent scans whose beams prove space free; each
            scan-to-scan match leaves out the points of both scans they saw through (people
            walking along with the robot; `scanguard.slam.free_space`). 0: match every point.
            None (default): 3 s with the ``graph`` back end, where it was measured to help,
            0 elsewhere (`RunConfig.free_space_horizon`).
        free_space_every: Seconds between two views kept for that.
        free_space_min_age: Only views at least this old test a point.
        free_space_margin: A beam proves a point gone only when it reaches this far beyond
            it (m, plus 3 % of the range), as do both neighbouring beams.
        free_space_lateral: ... and every beam within this many metres of it sideways (an
            edge placed a few centimetres off by the seed is not a person).
        operating_point: The CNN's threshold: ``adaptive`` (it starts at the calibrated one,
            or ``cnn_threshold``, and rises with this run's normal mode,
            `scanguard.detect.adaptive.AdaptiveThreshold`; no first pass, no reference) or
            ``fixed`` (the calibrated one throughout). Unset: `default_operating_point`.
        adaptive: Settings of the ``adaptive`` operating point.
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
    wheel_support: bool | None = None
    wheel_support_remedy: Literal["drop", "mask"] = "drop"
    free_space_horizon: float | None = Field(default=None, ge=0.0, le=60.0)
    free_space_every: float = Field(default=0.25, gt=0.0, le=60.0)
    free_space_min_age: float = Field(default=0.5, ge=0.0, le=60.0)
    free_space_margin: float = Field(default=0.25, ge=0.0, le=10.0)
    free_space_lateral: float = Field(default=0.0, ge=0.0, le=10.0)
    operating_point: OperatingPoint | None = None
    adaptive: AdaptiveConfig = Field(default_factory=lambda: AdaptiveConfig())

    def wheel_support_on(self, auto: bool = False) -> bool:
        """Whether the wheel-support test runs: ``wheel_support``, else ``auto``."""
        return auto if self.wheel_support is None else bool(self.wheel_support)

    def free_space_history(self, auto: float = 0.0) -> FreeSpaceHistory | None:
        """A fresh history of views for the scan-to-scan matcher (None when off).

        ``auto``: the horizon when ``free_space_horizon`` is unset (None).
        """
        horizon = auto if self.free_space_horizon is None else self.free_space_horizon
        if horizon <= 0.0:
            return None
        return FreeSpaceHistory(
            horizon,
            self.free_space_every,
            self.free_space_margin,
            self.free_space_min_age,
            self.free_space_lateral,
        )


def cnn_threshold(config: GuardConfig, detector: Any) -> float:
    """Effective CNN threshold: the configured one, else the detector's (0.5 without one)."""
    if config.cnn_threshold is not None:
        return float(config.cnn_threshold)
    return float(detector.threshold) if detector is not None else 0.5


def default_operating_point(backend: str) -> OperatingPoint:
    """The operating point when ``guard.operating_point`` is unset, per back end.

    ``adaptive`` with the ``graph`` and ``gmapping`` back ends, where leave one Freiburg log
    out chose it (graph: two folds of three, ACES 0.0454 -> 0.0440 m; GMapping, mean over
    filter seeds 0-2: three folds of three, ACES 0.0626 -> 0.0551 m; README, "An operating
    point that adapts online"); ``fixed`` with the scan-to-scan front end, where it was not
    measured in a run.
    """
    return "adaptive" if backend in ("graph", "gmapping") else "fixed"


def operating_point_detector(config: GuardConfig, detector: Any, backend: str = "frontend") -> Any:
    """The detector under the configured operating point (``adaptive``: wrapped, one per run).

    ``backend``: the back end the verdicts go to (the default when the config leaves it unset).

    The adaptive one starts from, and decides with, the effective `cnn_threshold`, so the
    gate built by `policy_gate` from the same config decides as the adaptive threshold does.
    """
    mode = config.operating_point or default_operating_point(backend)
    if detector is None or mode == "fixed":
        return detector
    return with_operating_point(detector, mode, config.adaptive, cnn_threshold(config, detector))


def baseline_threshold(config: GuardConfig, baseline: Any) -> float:
    """Effective baseline threshold: the configured one, else the judge's (0.5 without one)."""
    if config.baseline_threshold is not None:
        return float(config.baseline_threshold)
    return float(baseline.threshold) if baseline is not None else 0.5


def policy_gate(
    config: GuardConfig, detector: Any, baseline: Any, *, wheel_support: bool | None = None
) -> Gate:
    """The gate of the configured policy, with the effective thresholds.

    ``wheel_support`` (None: ``config.wheel_support_on()``) is the run's resolved setting.

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
    ws = config.wheel_support_on() if wheel_support is None else wheel_support
    return Gate(pol, cnn_threshold=t_cnn, baseline_threshold=t_base, wheel_support=ws)


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
        follower_beams: Where the wheel-support test fired: the beams whose points
            supported the matches over the wheels (what the matches followed), else None.
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
    follower_beams: NDArray[np.int64] | None = None

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
        free_space: Leave out of each match the points of both scans that the views of the
            last seconds saw through (`scanguard.slam.free_space`); None: match every point.
        wheel_support: Keeps the window of `scanguard.slam.wheel_support`; each verdict
            says whether its scan supports the wheels over the last matches (None: never).
    """

    def __init__(
        self,
        matcher: Matcher | Callable[..., Any],
        judge: Judge,
        *,
        min_points: int = 10,
        odometry_initial_guess: bool = False,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
        free_space: FreeSpaceHistory | None = None,
        wheel_support: WheelSupport | None = None,
    ) -> None:
        self.matcher = matcher
        self.wheel_support = wheel_support
        self.judge = judge
        self.min_points = min_points
        self.odometry_initial_guess = odometry_initial_guess
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self.index = 0
        self._previous: Frame | None = None
        self.free_space = free_space
        self._chain = np.zeros(3)  # sensor pose of the previous scan along the matches
        self._static_previous: Frame | None = None  # its points less the moving ones

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
            self._advance_chain(current, None)
            self._wheel_support(pair)
            return pair
        if current.odometry is not None and previous.odometry is not None:
            pair.odometry_increment = relative(previous.odometry, current.odometry)
        if pair.judged:
            self._match_and_judge(pair, previous, guess)
        elif pair.odometry_increment is not None:
            inc = robot_to_sensor_increment(pair.odometry_increment, self.laser_offset)
            self._advance_chain(current, inc)
        else:
            self._advance_chain(current, None)
        self._wheel_support(pair)
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
        static_previous, static_current = self._static_frames(previous, pair.current, initial)
        pair.match = match_frames(
            self.matcher,
            static_previous,
            static_current,
            min_points=self.min_points,
            initial=initial,
            index=pair.index,
        )
        pair.timings["match"] = time.perf_counter() - t
        pose = pair.match_pose
        # the chain follows the seed (wheels, or the prediction) where there is one: the match
        # is what the moving points bias, and a chain that followed it would see them static
        self._advance_chain(pair.current, pose if initial is None else initial)
        if pose is None:
            return
        pair.match_increment = sensor_to_robot_increment(pose, self.laser_offset)
        pair.centroid_match = centroid_distance_from_means(previous.mean, pair.current.mean, pose)
        pair.verdict = v = self.judge(previous, pair.current, pair.match, pair.odometry_increment)
        pair.timings["detect"], pair.timings["baseline"] = v.detect_seconds, v.baseline_seconds

    def _wheel_support(self, pair: JudgedPair) -> None:
        """Add the pair's scan to the wheel-support window; mark a verdict it fires on.

        The scan goes in with its match when the pair was judged and matched, else without
        (which breaks the window); a verdict whose scan supports the wheels over the last
        matches says so (``wheel_supported``).
        """
        if self.wheel_support is None:
            return
        frame, match = pair.current, pair.match_pose if pair.judged else None
        count = self.wheel_support.push(frame.scan.points(np.float64), frame.odometry, match)
        if pair.verdict is not None and self.wheel_support.fires(count):
            pair.verdict = replace(pair.verdict, wheel_supported=True)
            if count is not None and count.follower is not None:
                pair.follower_beams = np.flatnonzero(frame.scan.valid)[count.follower]

    def _static_frames(
        self, previous: Frame, current: Frame, initial: NDArray[np.float64] | None
    ) -> tuple[Frame, Frame]:
        """The two scans to match: without the points the recent views saw through.

        A scan keeps every point when the views would take half of them (a seed far off, or
        a scene that changed): the test assumes the seed is good to a few centimetres, and
        without a seed (the paper's ICP from the identity) nothing is left out.
        """
        if self.free_space is None or initial is None:
            self._static_previous = None
            return previous, current
        at = compose(self._chain, initial)
        moving = self.free_space.moving(current.points.astype(np.float64), at, current.scan.stamp)
        static = current
        if 0 < 2 * int(moving.sum()) < len(moving):
            static = replace(current, points=current.points[~moving])
        keep = self._static_previous
        self._static_previous = static
        return (keep if keep is not None and keep.scan is previous.scan else previous), static

    def _advance_chain(self, current: Frame, increment: NDArray[np.float64] | None) -> None:
        """Move the chain to the current scan and let the free-space history see it."""
        if self.free_space is None:
            return
        self._chain = chain(self._chain, increment)
        self.free_space.add(current.scan, self._chain)


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
