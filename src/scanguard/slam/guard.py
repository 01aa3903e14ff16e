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
from scanguard.slam.backend import MotionPrior
from scanguard.slam.gate import Gate
from scanguard.slam.grid import GridConfig, robot_to_sensor_increment, sensor_to_robot_increment
from scanguard.slam.judge import Judge, Verdict
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
