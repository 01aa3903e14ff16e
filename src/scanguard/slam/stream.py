"""The streaming guard: the paper's Figures 2 and 3 for one scan at a time, as a library.

`ScanGuard` is a thin use of the one per-scan step of every run (`scanguard.slam.loop.RunLoop`):
one back-end instance, the ``frontend`` (a scan-to-scan chain with its map), gated by the
guard's policy, on the paper's loop (``motion: odometry``). As each raw scan arrives it is
matched to the previous raw scan, the pair is judged (the CNN, a classical baseline, or both),
the gate decides, and the frontend moves:

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

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.geometry import as_pose
from scanguard.matching.registry import Matcher
from scanguard.scan import LaserScan, ScanSequence
from scanguard.slam.backend import FrontendBackend
from scanguard.slam.config import RunConfig
from scanguard.slam.gate import NonFiniteWatch
from scanguard.slam.grid import robot_to_sensor_increment
from scanguard.slam.guard import (
    GuardConfig,
    GuardCounts,
    JudgedPair,
    ScanPairs,
    operating_point_detector,
    policy_gate,
)
from scanguard.slam.judge import Detector, Judge, PairJudge, Verdict, check_detector_matcher
from scanguard.slam.loop import Instance, LoopStep, RunLoop, StepView
from scanguard.slam.metrics import centroid_distance_from_means
from scanguard.slam.wheel_support import WheelSupport

#: The guard's one instance in the loop (the gate of its policy).
_GATE = "cnn"


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


class _LastPair:
    """Sees each step of the loop (a `LoopObserver`): keeps the judged pair of the last one."""

    pair: JudgedPair | None = None

    def begin(self, seq: ScanSequence, names: Mapping[str, str]) -> None:
        """Nothing to set up."""

    def step(self, view: StepView) -> None:
        """Keep the step's pair (with its match, which the loop's record drops)."""
        self.pair = view.pair

    def end(self, trajectories: Mapping[str, Any], grids: Mapping[str, Any]) -> None:
        """Nothing to close."""


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
        self.matcher = matcher
        self.baseline = baseline
        self.gate = policy_gate(cfg, detector, baseline)
        if detector is not None:
            check_detector_matcher(detector, matcher, allow_other=allow_other_matcher)
        # ``operating_point: adaptive``: this guard's own threshold, learned from its scans
        self.detector = detector = operating_point_detector(cfg, detector)
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
        cv = cfg.motion_prior == "constant_velocity"
        self._run_config = RunConfig(
            backend="frontend",
            motion="odometry",
            prior="constant_velocity" if cv else "zero_motion",
            guard=cfg,
            compare=False,
        )
        self.frontend: FrontendBackend | None = None
        self._loop: RunLoop | None = None
        self._seen = _LastPair()
        self._watch = NonFiniteWatch()
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
    def counts(self) -> GuardCounts:
        """Scans by outcome since the last reset."""
        return self._loop.result.counts if self._loop is not None else GuardCounts()

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
        return self._watch.count

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
            free_space=cfg.free_space_history(),
            wheel_support=WheelSupport(self.laser_offset) if cfg.wheel_support_on() else None,
        )
        # the loop is built at the first scan, which says whether odometry comes with them;
        # the count restarts, but each detector's non-finite output is warned about once
        self._loop = None
        self._watch = NonFiniteWatch(warned=self._watch.warned)

    @property
    def index(self) -> int:
        """Scans seen since the last reset."""
        return self.pairs.index

    def _loop_for(self, odometry: ArrayLike | None) -> RunLoop:
        """The loop of this pass (built at its first scan: with or without odometry)."""
        if self._loop is None:
            self._loop = RunLoop(
                {_GATE: Instance(self._frontend, self.gate)},
                self.pairs,
                self._run_config,
                odometry=[] if odometry is not None else None,
                start=self._initial_pose,
                observer=self._seen,
            )
            self._loop.watch = self._watch
            self._loop.begin(None)
        return self._loop

    def step(
        self, scan: LaserScan, odometry: ArrayLike | None = None, judge: bool = True
    ) -> Decision:
        """Process one scan.

        Args:
            scan: The new raw scan.
            odometry: Absolute odometry pose ``(x, y, theta)`` of the robot at ``scan.stamp``
                (only increments between consecutive calls are used), or None. A guard given
                odometry with its first scan needs it with every scan until `reset`.
            judge: Match and judge the pair. False skips the (expensive) matcher and
                detectors, for a scan no back end wants: the scan only becomes the previous
                scan of the next step, the pose moves as on a reject (odometry increment, else
                the motion prior) and the decision has reason ``"skipped"`` (not accepted, NaN
                scores). The first scan is never judged, so ``judge`` does not change it.

        Returns:
            The decision for this scan.

        Raises:
            ConfigError: Odometry given with some scans of a pass and not with others.
        """
        t_start = time.perf_counter()
        loop = self._loop_for(odometry)
        odom = None if odometry is None else as_pose(odometry).reshape(3)
        k = len(loop.result.steps)
        step = loop.feed(scan, odom, judge=judge)
        timings = {**step.timings, "map": float(loop.result.backend_seconds[_GATE][k])}
        timings["total"] = time.perf_counter() - t_start
        assert self._seen.pair is not None  # the loop showed this step to its observer
        return self._decision(self._seen.pair, step, timings)

    def _decision(self, pair: JudgedPair, step: LoopStep, timings: dict[str, float]) -> Decision:
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
            accepted=step.accepted,
            reason=step.reason,
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
