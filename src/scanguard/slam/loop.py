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

import logging
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import BackendError, ConfigError
from scanguard.geometry import compose, relative
from scanguard.pairs.labels import LabelConfig
from scanguard.runtime.executor import side_by_side
from scanguard.scan import LaserScan
from scanguard.slam.backend import Backend
from scanguard.slam.config import RunConfig
from scanguard.slam.detached import DetachedBackend, DetachedGroup
from scanguard.slam.gate import REJECTED_WHEELS, Gate, NonFiniteWatch
from scanguard.slam.grid import robot_to_sensor_increment
from scanguard.slam.guard import JudgedPair, ScanPairs, policy_gate
from scanguard.slam.judge import Verdict
from scanguard.slam.loop_records import (
    LoopObserver,
    LoopResult,
    LoopStep,
    OnStep,
    StepView,
    without_arrays,
)
from scanguard.slam.motion import FusedMotion, MotionStep, match_information
from scanguard.slam.oracle import pair_label

__all__ = [
    "GATES",
    "Instance",
    "LoopObserver",
    "LoopResult",
    "LoopStep",
    "OnStep",
    "RunLoop",
    "StepView",
    "instance_gates",
    "trajectory_name",
    "trajectory_names",
]

logger = logging.getLogger(__name__)

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
    policy = policy_gate(config.guard, detector, baseline, wheel_support=config.wheel_support())
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
        on_wait: Called once when the scans are all fed and the loop is about to wait for its
            instances on threads or in worker processes (the caller's idle time: e.g. to load
            what it will write with).
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
        on_wait: Callable[[], None] | None = None,
    ) -> None:
        self.instances = instances
        self.pairs = pairs
        self.config = config
        self.labels_rule: LabelConfig = config.labels or LabelConfig()
        self.odom = odometry
        self.ref_sensor = reference_sensor
        self.on_step = on_step
        self.observer = observer
        self.on_wait = on_wait
        self.fused = config.motion == "fused"
        self.by_matches = config.motion in ("guarded_matches", "fused")
        self.map_rejected = config.maps_rejected_scans()
        self.wheel_mask = config.guard.wheel_support_remedy == "mask"
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
        self._lane: DetachedGroup | None = None  # this process's instances on a thread
        self._detached = {
            g: i.backend for g, i in instances.items() if isinstance(i.backend, DetachedBackend)
        }
        if self._detached and (not self.fused or observer is not None):
            raise ConfigError(
                "instances in worker processes need motion: fused (their inputs must not "
                "depend on any back end) and no observer (it reads every instance's pose)"
            )

    def run(self, scans: Sequence[LaserScan]) -> LoopResult:
        """Feed every scan to every instance; the `LoopResult`.

        With `RunConfig.pipelines` and no observer, the instances of this process update on
        a thread of their own while the loop goes on (`scanguard.slam.detached`).
        """
        self.begin(len(scans))
        if self.observer is None and self.config.pipelines():
            self._pipeline()
        try:
            for scan in scans:
                self.feed(scan)
            return self.finish()
        except BaseException:
            self.abort()
            raise

    def _pipeline(self) -> None:
        """Hand the instances of this process to a thread of their own (`DetachedGroup`)."""
        local = {g: i.backend for g, i in self.instances.items() if g not in self._detached}
        if not local:
            return
        group = DetachedGroup.on_thread(local, self.config)
        for g in local:
            self._detached[g] = DetachedBackend(group, g)
        self._lane = group

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
        step.motion = without_arrays(step.motion)
        if self._previous is not None and self._lane is None:  # else the thread releases it
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
        self._collect_detached(res, n)
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

    def _collect_detached(self, res: LoopResult, n: int) -> None:
        """Wait for the instances in worker processes; put their results in their place."""
        if self._detached:
            logger.info(
                "waiting for the back-end instances on threads or in worker processes (gates %s)",
                ", ".join(sorted(self._detached)),
            )
            if self.on_wait is not None:
                self.on_wait()
        for g, proxy in self._detached.items():
            got = proxy.result()
            if len(got.wanted) != n or len(got.seconds) != n:
                raise BackendError(
                    f"the {g!r} instance's worker processed {len(got.wanted)} of {n} scans"
                )
            res.wanted[g], res.backend_seconds[g] = got.wanted, got.seconds
            if got.finished is not None:  # else the instance on a thread: it stayed here
                self.instances[g].backend = got.finished
        self._detached = {}
        self._lane = None

    def abort(self) -> None:
        """Stop the instances' threads and worker processes (a run that failed)."""
        for proxy in self._detached.values():
            proxy.abort()
        self.close()

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
        # a rejected scan still reaches a back end that maps rejected scans, unless its own
        # points showed the match following something moving (the back end's match would
        # too): then it reaches it without those points (``mask``), or not at all (``drop``)
        masked = self._masked(scan, pair)
        scans: dict[str, LaserScan] = {}
        reaches: dict[str, bool] = {}
        for g, d in decided.items():
            wheels = d.reason == REJECTED_WHEELS
            scans[g] = masked if wheels and masked is not None else scan
            reaches[g] = usable[g] or (self.map_rejected and (not wheels or masked is not None))
        reason = pair.reason(decided["cnn"].reason)
        res.counts.add(reason)
        timings = {**pair.timings, "total": time.perf_counter() - t0}
        if self.fused:
            self._move_fused(k, scan, pair, usable, odo_k, res)
        elif self.by_matches:
            self._move_by_matches(k, scan, pair, usable, odo_k, res)
        self._update(k, scans, pair.match_pose, odo_k, reaches, res)
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
                step = self._fusion[g].step(
                    dt,
                    wheel,
                    None if info is None else np.asarray(pair.match_increment),
                    info,
                    eig_min_per_inlier=float("nan") if eig is None else eig,
                    fault_probability=p_fault,
                    rejected=not usable[g],
                )
                self._motion[g] = step
                self._motion_pose[g] = compose(self._motion_pose[g], step.increment)
            odo_k[g] = self._motion_pose[g].copy()
            if g not in self._detached:  # a worker asks its instance (the same question)
                res.wanted[g][k] = bool(inst.backend.wants_scan(scan.stamp, odo_k[g]))

    def _masked(self, scan: LaserScan, pair: JudgedPair) -> LaserScan | None:
        """With ``wheel_support_remedy: mask``: the scan without what the matches followed."""
        beams = pair.follower_beams
        if not self.wheel_mask or beams is None:
            return None
        ranges = np.array(scan.ranges, dtype=np.float32)
        ranges[beams] = np.nan  # no return: proves nothing to a map or a view
        return scan.with_ranges(ranges)

    def _update(
        self,
        k: int,
        scans: dict[str, LaserScan],
        match: NDArray[np.float64] | None,
        odo_k: dict[str, NDArray[np.float64]],
        reaches: dict[str, bool],
        res: LoopResult,
    ) -> None:
        """Feed the scan to every instance, as usable where ``reaches`` says so; keep the prior.

        With several instances and `RunConfig.instance_workers` above 1 they update side by
        side on a thread pool: each reads only its own state, the scan (whose derived arrays
        are read-only and recomputed identically) and this step's values, so the results are
        the same as one after the other. An instance in a worker process
        (`scanguard.slam.detached`) is handed the same values, and goes on there.
        """

        def one(g: str) -> None:
            inst, t0, scan = self.instances[g], time.perf_counter(), scans[g]
            own = match
            if self.fused and k > 0 and match is not None:
                # a scan-to-scan back end chains this instance's fused step, not the raw match
                own = robot_to_sensor_increment(self._motion[g].increment, self.pairs.laser_offset)
            cov = self._motion[g].covariance if self.fused and k > 0 else None
            use = reaches[g]
            detached = self._detached.get(g)
            if detached is not None:
                detached.submit(scan, odo_k[g], usable=use, match=own, covariance=cov)
                return
            if cov is not None:
                setter = getattr(inst.backend, "set_motion_covariance", None)
                if setter is not None:  # a back end whose motion model reads the fused noise
                    setter(cov)
            inst.backend.update(scan, odo_k[g], usable=use, match=own)
            res.backend_seconds[g][k] = time.perf_counter() - t0

        for g in self._detached:
            one(g)
        local = [g for g in self.instances if g not in self._detached]
        pool = self._instance_pool(len(local))
        if pool is None:
            for g in local:
                one(g)
        else:
            side_by_side(pool, [partial(one, g) for g in local])
        if self.odom is None and not self.by_matches:
            for g, inst in self.instances.items():
                pose = np.asarray(inst.backend.pose, dtype=np.float64).reshape(3)
                prev = self._last_pose[g]
                self._last_inc[g] = np.zeros(3) if prev is None else relative(prev, pose)
                self._last_pose[g] = pose.copy()

    def _instance_pool(self, n_local: int) -> ThreadPoolExecutor | None:
        """The threads of the ``n_local`` instances' updates (made on first use), or None."""
        if self._pool is None:
            n = self.config.instance_workers(n_local)
            if n > 1:
                self._pool = ThreadPoolExecutor(n, thread_name_prefix="scanguard-instance")
        return self._pool

    def close(self) -> None:
        """Stop the instances' threads (`finish` does; a later `feed` starts them again)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
