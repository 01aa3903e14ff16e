"""The per-scan loop of a guarded run: one pass over the scans feeds several back-end instances.

Every instance (`Instance`) is one back end (`scanguard.slam.registry`), built with the same
settings and seed, and one gate (`scanguard.slam.gate.Gate`) that says which scans it may use:

(a) ``<backend>`` - unguarded (gate ``none``): every scan is usable (for ``frontend``: plain
    ICP chaining);
(b) ``<backend>+cnn`` - guarded by the guard's configured policy (the CNN by default);
(c) ``<backend>+baseline`` - guarded by a classical detector (when one is given);
(d) ``<backend>+oracle`` - guarded by reference-based labels (`scanguard.slam.oracle`, the rule
    the training data was labelled with), computed on the fly for each judged pair: the upper
    bound of any gate (only with a reference).

A scan is matched and judged (`scanguard.slam.guard.ScanPairs`) only when at least one instance
``wants_scan`` it, and only once; every instance's gate then decides on that one verdict, so all
instances see exactly the same matches.

A recording without odometry runs with a motion prior that does not know the answer
(``RunConfig.prior``): each instance gets pseudo-odometry built from its *own* estimate, either
a constant pose (``zero_motion``) or its last pose increment repeated (``constant_velocity``).
With ``RunConfig.motion = "guarded_matches"`` every scan is judged and each instance moves by
the match where its own gate accepts it, and by odometry (or the prior) where it does not.
With ``RunConfig.motion = "fused"`` (the default) every scan is judged and each instance moves
by its own fused motion (`scanguard.slam.motion.FusedMotion`): the wheels, the match where its
gate accepts it, and a constant-velocity prediction, weighted by their information; the
unguarded instance accepts every match and never flags the wheels.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import ConfigError
from scanguard.geometry import compose, relative
from scanguard.pairs.labels import LabelConfig
from scanguard.scan import LaserScan, ScanSequence
from scanguard.slam.backend import Backend
from scanguard.slam.config import RunConfig
from scanguard.slam.gate import Gate, GateDecision, NonFiniteWatch
from scanguard.slam.grid import robot_to_sensor_increment
from scanguard.slam.guard import GuardCounts, JudgedPair, ScanPairs, policy_gate
from scanguard.slam.judge import Verdict
from scanguard.slam.motion import FusedMotion, MotionStep, match_information
from scanguard.slam.oracle import pair_label

#: Gates of the back-end instances, in report order (``none`` = unguarded).
GATES = ("none", "cnn", "baseline", "oracle")


def trajectory_name(backend: str, gate: str) -> str:
    """Trajectory name of a back-end instance: ``gmapping`` (unguarded), ``gmapping+cnn``..."""
    return backend if gate == "none" else f"{backend}+{gate}"


def trajectory_names(backend: str) -> tuple[str, ...]:
    """All trajectory names of a run with ``backend``, in report order."""
    return ("odometry", *(trajectory_name(backend, g) for g in GATES))


def instance_gates(
    config: RunConfig, gates: Sequence[str], detector: Any, baseline: Any
) -> dict[str, Gate]:
    """The gate of each instance: ``none`` (every scan usable), the guard's policy for ``cnn``.

    Raises:
        ConfigError: The policy needs a detector that was not given, or a threshold is invalid.
    """
    policy = policy_gate(config.guard, detector, baseline)
    every: dict[str, Gate] = {
        "none": policy.of_kind("none", require_match=False),
        "cnn": policy,
        "baseline": policy.of_kind("baseline"),
        "oracle": policy.of_kind("oracle"),
    }
    return {g: every[g] for g in gates}


@dataclass
class Instance:
    """One back-end instance of a run: a back end and the gate of the scans it may use."""

    backend: Backend
    gate: Gate


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
        motion: Gate -> that instance's fused-motion counts (``match``, ``wheels``,
            ``flagged``, ``prediction_only``: steps that used each source) and its fitted wheel
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


def _without_arrays(motion: MotionStep | None) -> MotionStep | None:
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


class RunLoop:
    """The loop over one recording (see the module docstring).

    `run` feeds a whole recording; a stream (a live node) calls `begin`, then `feed` for each
    scan as it arrives, then `finish`: the same per-scan step either way.

    Args:
        instances: Gate name -> instance (``none`` and ``cnn`` at least).
        pairs: Matches and judges consecutive scans.
        config: Run settings (``motion``, ``prior``).
        odometry: Robot odometry poses ``(N, 3)``, ``[]`` for poses that arrive with each scan
            (`feed`), or None (the prior then moves each instance).
        start: Robot pose of the first scan.
        reference_sensor: Reference sensor poses ``(N, 3)`` for the oracle labels, or None.
        on_step: Called after every scan with ``(step, n_accepted, n_rejected)``.
        observer: Sees every scan after the instances (`LoopObserver.step`), or None.
    """

    def __init__(
        self,
        instances: dict[str, Instance],
        pairs: ScanPairs,
        config: RunConfig,
        *,
        odometry: NDArray[np.float64] | list[NDArray[np.float64]] | None,
        start: NDArray[np.float64],
        reference_sensor: NDArray[np.float64] | None = None,
        on_step: OnStep | None = None,
        observer: LoopObserver | None = None,
    ) -> None:
        self.instances = instances
        self.pairs = pairs
        self.config = config
        self.labels_rule: LabelConfig = config.labels or LabelConfig()
        self.odom = odometry
        self.ref_sensor = reference_sensor
        self.on_step = on_step
        self.observer = observer
        self.fused = config.motion == "fused"
        self.by_matches = config.motion in ("guarded_matches", "fused")
        self.map_rejected = config.maps_rejected_scans()
        self._fusion = {g: FusedMotion(config.fusion, flag_wheels=g != "none") for g in instances}
        self._motion: dict[str, MotionStep] = {}
        self._prev_stamp: float | None = None
        self.cv = config.prior == "constant_velocity"
        self.watch = NonFiniteWatch()
        start = np.asarray(start, dtype=np.float64)
        self._pseudo = {g: start.copy() for g in instances}
        self._motion_pose = {g: start.copy() for g in instances}
        self._last_pose: dict[str, NDArray[np.float64] | None] = dict.fromkeys(instances)
        self._last_inc = {g: np.zeros(3) for g in instances}
        self.result = LoopResult()  # of the pass `begin` starts
        self._k = 0
        self._previous: LaserScan | None = None
        self._pool: ThreadPoolExecutor | None = None

    def run(self, scans: Sequence[LaserScan]) -> LoopResult:
        """Feed every scan to every instance; the `LoopResult`."""
        self.begin(len(scans))
        for scan in scans:
            self.feed(scan)
        return self.finish()

    def begin(self, n: int | None = None) -> None:
        """Start a pass over scans that are then given one at a time (`feed`).

        Args:
            n: Number of scans, when known (the per-scan arrays are sized once); None for a
                stream (they grow as scans arrive).
        """
        size = 0 if n is None else n
        self.result = LoopResult(
            backend_seconds={g: np.zeros(size) for g in self.instances},
            wanted={g: np.zeros(size, dtype=bool) for g in self.instances},
        )
        self._k = 0
        self._previous = None

    def feed(
        self, scan: LaserScan, odometry: NDArray[np.float64] | None = None, *, judge: bool = True
    ) -> LoopStep:
        """Feed the next scan to every instance (after `begin`); what the loop did with it.

        Args:
            scan: The next scan.
            odometry: Robot odometry pose of ``scan``, for a loop built with
                ``odometry=[]`` (a stream: the poses arrive with the scans); None otherwise
                (a loop built with an odometry array reads it, one without uses its prior).
            judge: False: the caller wants this scan neither matched nor judged (it is
                handled like a reject, reason ``skipped``; the streaming guard's option).

        Raises:
            ConfigError: A pose for a loop without streamed odometry, or none for one with.
        """
        k, res = self._k, self.result
        if odometry is not None or isinstance(self.odom, list):
            if not isinstance(self.odom, list) or odometry is None:
                raise ConfigError(
                    "RunLoop.feed: an odometry pose goes with every scan of a loop built with "
                    "odometry=[] (and with no other)"
                )
            self.odom.append(np.asarray(odometry, dtype=np.float64).reshape(3))
        for arrays in (res.backend_seconds, res.wanted):
            for g, a in arrays.items():
                if k >= len(a):  # a stream: grow by doubling
                    arrays[g] = np.concatenate([a, np.zeros(max(16, len(a)), dtype=a.dtype)])
        step = self._scan(k, scan, res, judge)
        res.steps.append(step)
        self._k += 1
        if self.on_step is not None:
            self.on_step(step, res.counts.accepted, res.counts.rejected)
        # Memory stays bounded by the window the loop needs, not the recording: the
        # step keeps the numbers of decisions.csv, not the match with its arrays, and
        # the previous scan's cached points go (a back end that needs them recomputes
        # the same values).
        step.match = None
        step.motion = _without_arrays(step.motion)
        if self._previous is not None:
            self._previous.release()
        self._previous = scan
        return step

    def finish(self) -> LoopResult:
        """End the pass: the `LoopResult` of the scans fed since `begin`."""
        self.close()
        res, n = self.result, self._k
        res.backend_seconds = {g: a[:n] for g, a in res.backend_seconds.items()}
        res.wanted = {g: a[:n] for g, a in res.wanted.items()}
        res.non_finite = self.watch.count
        if self.fused:
            for g, f in self._fusion.items():
                scale = dict(zip(("x", "y", "theta"), f.wheels.scale, strict=True))
                res.motion[g] = {
                    **f.counts,
                    **{f"wheel_scale_{a}": float(v) for a, v in scale.items()},
                }
                if f.hat is not None:  # the match's fitted variance scale (three-cornered)
                    for a, v in zip(("x", "y", "theta"), f.hat.match_scale, strict=True):
                        res.motion[g][f"match_scale_{a}"] = float(v)
        return res

    def _odometry(self, k: int) -> dict[str, NDArray[np.float64]]:
        """Each instance's odometry pose at scan ``k`` (its pseudo-odometry without odometry)."""
        if self.odom is not None:
            return {g: self.odom[k] for g in self.instances}
        if k > 0 and self.cv:
            for g in self.instances:
                self._pseudo[g] = compose(self._pseudo[g], self._last_inc[g])
        return {g: self._pseudo[g].copy() for g in self.instances}

    def _scan(self, k: int, scan: LaserScan, res: LoopResult, wanted: bool = True) -> LoopStep:
        odo_k = self._odometry(k)
        if not self.by_matches:
            for g, inst in self.instances.items():
                res.wanted[g][k] = bool(inst.backend.wants_scan(scan.stamp, odo_k[g]))
        judge = wanted and (self.by_matches or bool(any(w[k] for w in res.wanted.values())))
        t0 = time.perf_counter()
        guess = self._seed(k, scan.stamp)
        odom_k = None if self.odom is None else self.odom[k]
        pair = self.pairs.step(scan, odom_k, judge=judge, guess=guess)
        self.watch(pair.verdict, pair.index)
        verdict = self._labelled(k, pair, res.labels)
        decided = {g: inst.gate.decide(verdict) for g, inst in self.instances.items()}
        first = pair.previous is None
        usable = {g: first or d.accepted for g, d in decided.items()}
        reason = pair.reason(decided["cnn"].reason)
        res.counts.add(reason)
        timings = {**pair.timings, "total": time.perf_counter() - t0}
        if self.fused:
            self._move_fused(k, scan, pair, usable, odo_k, res)
        elif self.by_matches:
            self._move_by_matches(k, scan, pair, usable, odo_k, res)
        self._update(k, scan, pair.match_pose, odo_k, usable, res)
        step = LoopStep(
            index=pair.index,
            stamp=scan.stamp,
            accepted=usable["cnn"],
            reason=reason,
            match=pair.match,
            verdict=verdict,
            match_increment=pair.match_increment,
            centroid_match=pair.centroid_match,
            timings=timings,
            motion=self._motion.get("cnn") if k > 0 else None,
        )
        if self.observer is not None:
            self.observer.step(
                StepView(
                    scan=scan,
                    step=step,
                    pair=pair,
                    decisions=decided,
                    usable=usable,
                    wanted={g: bool(w[k]) for g, w in res.wanted.items()},
                    poses={g: i.backend.pose for g, i in self.instances.items()},
                )
            )
        return step

    def _seed(self, k: int, stamp: float) -> NDArray[np.float64] | None:
        """The matcher's initial guess (robot frame) under ``fusion.seed_match``, or None."""
        seed = self.config.fusion.seed_match
        if not self.fused or seed == "none" or k == 0:
            return None
        if seed == "wheels" and self.odom is not None:
            return relative(self.odom[k - 1], self.odom[k])
        if self._prev_stamp is None:
            return None
        return self._fusion["cnn"].prediction(stamp - self._prev_stamp)

    def _labelled(self, k: int, pair: JudgedPair, labels: dict[int, int]) -> Verdict | None:
        """The verdict with the reference label of the pair (stored in ``labels``)."""
        if self.ref_sensor is None or not pair.judged:
            return pair.verdict
        labels[k] = pair_label(
            pair.match_pose,
            relative(self.ref_sensor[k - 1], self.ref_sensor[k]),
            pair.current.scan.points(np.float64),
            self.labels_rule,
        )
        return None if pair.verdict is None else replace(pair.verdict, reference_label=labels[k])

    def _move_by_matches(
        self,
        k: int,
        scan: LaserScan,
        pair: JudgedPair,
        usable: dict[str, bool],
        odo_k: dict[str, NDArray[np.float64]],
        res: LoopResult,
    ) -> None:
        """Each instance's own "odometry": its gate's accepted matches, else odometry/prior."""
        odom = self.odom
        wheel = relative(odom[k - 1], odom[k]) if odom is not None and k > 0 else np.zeros(3)
        for g, inst in self.instances.items():
            if k > 0:
                use = usable[g] and pair.match is not None
                step = np.asarray(pair.match_increment) if use else wheel
                if odom is None and not use and self.cv:
                    step = self._last_inc[g]
                self._motion_pose[g] = compose(self._motion_pose[g], step)
                if odom is None:
                    self._last_inc[g] = step
            odo_k[g] = self._motion_pose[g].copy()
            res.wanted[g][k] = bool(inst.backend.wants_scan(scan.stamp, odo_k[g]))

    def _move_fused(
        self,
        k: int,
        scan: LaserScan,
        pair: JudgedPair,
        usable: dict[str, bool],
        odo_k: dict[str, NDArray[np.float64]],
        res: LoopResult,
    ) -> None:
        """Each instance's "odometry": the chain of its fused motion (`FusedMotion`)."""
        dt = 0.0 if self._prev_stamp is None else scan.stamp - self._prev_stamp
        self._prev_stamp = scan.stamp
        odom, m = self.odom, pair.match
        wheel = relative(odom[k - 1], odom[k]) if odom is not None and k > 0 else None
        info = eig = None
        cfg = self.config.fusion
        pose, hessian = pair.match_pose, getattr(m, "hessian", None)
        n_in = int(getattr(m, "n_inliers", 0))
        # a matcher that reports no Hessian brings no information: its match is judged and
        # mapped, but the fused motion follows the wheels and the prediction
        if pose is not None and hessian is not None and n_in >= cfg.match_min_inliers:
            info = match_information(hessian, n_in, pose, self.pairs.laser_offset, cfg.match_sigma)
            # the matcher's own eigenvalues where it reports them (MatchResult does)
            ev = getattr(m, "eigenvalues", None)
            lo = float(ev[0]) if ev is not None else float(np.linalg.eigvalsh(hessian)[0])
            eig = lo / n_in
        p_fault = pair.verdict.probability if pair.verdict is not None else float("nan")
        for g, inst in self.instances.items():
            if k > 0:
                use = usable[g] and info is not None
                step = self._fusion[g].step(
                    dt,
                    wheel,
                    np.asarray(pair.match_increment) if use else None,
                    info if use else None,
                    eig_min_per_inlier=float("nan") if eig is None else eig,
                    fault_probability=p_fault,
                )
                self._motion[g] = step
                self._motion_pose[g] = compose(self._motion_pose[g], step.increment)
            odo_k[g] = self._motion_pose[g].copy()
            res.wanted[g][k] = bool(inst.backend.wants_scan(scan.stamp, odo_k[g]))

    def _update(
        self,
        k: int,
        scan: LaserScan,
        match: NDArray[np.float64] | None,
        odo_k: dict[str, NDArray[np.float64]],
        usable: dict[str, bool],
        res: LoopResult,
    ) -> None:
        """Feed the scan to every instance (and track each one's last increment for the prior).

        With several instances and `RunConfig.instance_workers` above 1 they update side by
        side on a thread pool: each reads only its own state, the scan (whose derived arrays
        are read-only and recomputed identically) and this step's values, so the results are
        the same as one after the other.
        """

        def one(g: str) -> None:
            inst, t0 = self.instances[g], time.perf_counter()
            own = match
            if self.fused and k > 0 and match is not None:
                # a scan-to-scan back end chains this instance's fused step, not the raw match
                own = robot_to_sensor_increment(self._motion[g].increment, self.pairs.laser_offset)
            if self.fused and k > 0:
                setter = getattr(inst.backend, "set_motion_covariance", None)
                if setter is not None:  # a back end whose motion model reads the fused noise
                    setter(self._motion[g].covariance)
            inst.backend.update(scan, odo_k[g], usable=usable[g] or self.map_rejected, match=own)
            res.backend_seconds[g][k] = time.perf_counter() - t0

        pool = self._instance_pool()
        if pool is None:
            for g in self.instances:
                one(g)
        else:
            futures = [pool.submit(one, g) for g in self.instances]
            wait(futures)  # every instance finishes this scan before an error is raised
            for f in futures:
                f.result()
        if self.odom is None and not self.by_matches:
            for g, inst in self.instances.items():
                pose = np.asarray(inst.backend.pose, dtype=np.float64).reshape(3)
                prev = self._last_pose[g]
                self._last_inc[g] = np.zeros(3) if prev is None else relative(prev, pose)
                self._last_pose[g] = pose.copy()

    def _instance_pool(self) -> ThreadPoolExecutor | None:
        """The threads of the instances' updates (made on first use), or None for one thread."""
        if self._pool is None:
            n = self.config.instance_workers(len(self.instances))
            if n > 1:
                self._pool = ThreadPoolExecutor(n, thread_name_prefix="scanguard-instance")
        return self._pool

    def close(self) -> None:
        """Stop the instances' threads (`finish` does; a later `feed` starts them again)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
