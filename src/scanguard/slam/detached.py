"""Back-end instances in a process of their own: a run's comparisons on the other core.

With ``motion: fused`` nothing a back-end instance receives depends on any back end's state:
per scan, the scan, the instance's own fused odometry pose and covariance, its gate's decision
and its fused step. The loop (`scanguard.slam.loop.RunLoop`) can therefore hand a comparison
instance's inputs to a worker process and go on with the next scan; the worker runs the calls
the loop would have made (``wants_scan``, ``set_motion_covariance``, ``update``), in the same
order with the same values, so its results are those of the instance run in the loop's
process, bit for bit. When the recording is over it sends back what the writers read
(`scanguard.slam.backend.FinishedBackend`), and the loop puts that in the instance's place.

The guarded instance stays in the loop's process beside its comparisons (all of them in one
worker measured slower). Alone (no comparison) it goes to a worker too where its back end needs
no CNN (`needs_detector`): its gate (the adaptive operating point) learns in the loop's
process either way, since the loop makes every decision and hands the instance its result. An
observer or a live node reads every instance at every scan, so none of theirs leaves. The worker's
instances go through each batch of scans side by side on threads (`InstancesHandler`), so that
the worker uses both cores once the loop's process has finished its own scans.

For the same reason the instances that stay in the loop's process can update on a thread of
their own, a few scans behind the loop (`DetachedGroup.on_thread`): the loop matches and
judges the next scans meanwhile, on the other core. They are the same objects, fed the same
calls in the same order, so nothing but the time changes.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import BackendError, ConfigError
from scanguard.matching.lanes import set_search_lanes
from scanguard.runtime.streaming import ProcessStream, ThreadStream
from scanguard.scan import LaserScan
from scanguard.slam.backend import Backend, FinishedBackend
from scanguard.slam.config import RunConfig

logger = logging.getLogger(__name__)

#: The comparisons' gates: their instances may run in a worker (their closure judges need no
#: detector); the guarded ``cnn`` instance may too where `needs_detector` says it can.
DETACHABLE = ("none", "baseline", "oracle")


@dataclass(frozen=True, slots=True)
class DetachedStep:
    """What the loop would hand one instance for one scan (see `RunLoop`'s ``_update``)."""

    gate: str
    scan: LaserScan
    odometry: NDArray[np.float64]
    usable: bool
    match: NDArray[np.float64] | None
    covariance: NDArray[np.float64] | None


@dataclass
class DetachedResult:
    """What a worker sends back for one instance.

    Attributes:
        wanted: Per scan: what its ``wants_scan`` said (before the scan's update).
        seconds: Per scan: seconds of its ``set_motion_covariance`` and ``update``.
        finished: Its results (`FinishedBackend`); None for an instance on a thread of the
            loop's own process, which stays in its place.
    """

    wanted: NDArray[np.bool_]
    seconds: NDArray[np.float64]
    finished: FinishedBackend | None


#: What a worker started ahead loads while the run reads its recording
#: (`scanguard.runtime.streaming.prestart_worker`).
WORKER_WARM_UP = ("scanguard.slam.registry", "scanguard.slam.detached:warm_up")


def warm_up() -> None:
    """Load a graph instance's kernels in this process (a worker's warm-up).

    Four synthetic scans of a 4 m square room, the robot creeping along it, through a default
    `scanguard.slam.graph.GraphBackend`: the compiled matching kernels load from the cache
    before the first real scan, not on it.
    """
    from scanguard.slam.graph import GraphBackend

    backend = GraphBackend(range_max=10.0)
    angles = np.linspace(-2.0, 2.0, 400)
    c, s = np.cos(angles), np.sin(angles)
    for k in range(4):
        x = 0.12 * k
        with np.errstate(divide="ignore"):
            to_x = np.where(c > 0, (2.0 - x) / c, np.where(c < 0, (-2.0 - x) / c, np.inf))
            to_y = np.where(s != 0, 2.0 / np.abs(s), np.inf)
        r = np.minimum(to_x, to_y).astype(np.float32)
        backend.update(LaserScan(0.1 * k, r, -2.0, 4.0 / 399, 0.05, 10.0), np.array([x, 0.0, 0.0]))


@dataclass(frozen=True)
class InstancesSpec:
    """The back ends of a worker, built there as `scanguard.slam.registry.make_backend` would.

    Attributes:
        config: The run's resolved settings.
        gates: The gates of its instances (none whose back end `needs_detector`).
        laser_offset: Pose of the laser in the robot frame.
        start: Robot pose of the first scan.
        range_max: The sensor's largest range (m), or None.
        reference: Reference robot poses (the oracle's closure judge, report labels), or None.
    """

    config: RunConfig
    gates: tuple[str, ...]
    laser_offset: NDArray[np.float64]
    start: NDArray[np.float64]
    range_max: float | None
    reference: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        from scanguard.slam.registry import needs_detector

        wrong = [g for g in self.gates if g not in (*DETACHABLE, "cnn")]
        wrong += [g for g in self.gates if needs_detector(self.config, g)]
        if wrong:
            raise ConfigError(f"instances of gates {wrong} cannot run in a worker process")

    def build(self) -> InstancesHandler:
        """The instances, in the worker."""
        from scanguard.slam.registry import closure_judge_for, make_backend

        def one(gate: str) -> Backend:
            judge = closure_judge_for(self.config, gate, None, self.laser_offset, self.reference)
            return make_backend(
                self.config,
                laser_offset=self.laser_offset,
                initial_pose=self.start,
                range_max=self.range_max,
                closure_judge=judge,
                reference=self.reference,
            )

        threads = self.config.instance_workers(len(self.gates))
        if len(self.gates) == 1 and (os.cpu_count() or 1) > 1:
            # one instance here beside the guard's process: once the guard is done with the
            # recording, the wide searches take the second core (same results)
            set_search_lanes(2)
        return InstancesHandler({g: one(g) for g in self.gates}, threads=threads)


@dataclass
class _Lane:
    """Some instances' steps, each instance's in order: one thread's work (`InstancesHandler`)."""

    backends: dict[str, Backend]
    wanted: dict[str, list[bool]]
    seconds: dict[str, list[float]]
    _last: LaserScan | None = None

    def feed(self, items: list[DetachedStep]) -> None:
        """The calls the loop makes for each step, then the scans it is done with released."""
        for item in items:
            backend = self.backends[item.gate]
            self.wanted[item.gate].append(bool(backend.wants_scan(item.scan.stamp, item.odometry)))
            t0 = time.perf_counter()
            if item.covariance is not None:
                setter = getattr(backend, "set_motion_covariance", None)
                if setter is not None:
                    setter(item.covariance)
            backend.update(item.scan, item.odometry, usable=item.usable, match=item.match)
            self.seconds[item.gate].append(time.perf_counter() - t0)
            # a scan is released when this lane moves on to the next one: another lane still
            # behind it computes its derived arrays again, identically
            if self._last is not None and self._last is not item.scan:
                self._last.release()
            self._last = item.scan

    def finish(self) -> None:
        """Nothing to return: the results are read from the instances."""


@dataclass
class InstancesHandler:
    """Feeds each `DetachedStep` to its instance (in the worker, or on the loop's thread).

    With ``threads`` above 1 the instances are spread over that many lanes, each on a thread
    of its own (`ThreadStream`) with its own queue: an instance takes its steps in order and
    reads only its own state, the scan (whose derived arrays are read-only and recomputed
    identically) and its step's values, so the results are those of one after the other,
    and no lane waits for another (a loop search of one instance, tens of ms, no longer holds
    the others at the end of a batch). One lane: the steps are taken on the caller's thread.
    """

    backends: dict[str, Backend]
    threads: int = 1
    snapshot: bool = True  # False: `finish` leaves the instances where they are (a thread's)
    wanted: dict[str, list[bool]] = field(default_factory=dict)
    seconds: dict[str, list[float]] = field(default_factory=dict)
    _inline: _Lane | None = None
    _lanes: dict[str, ThreadStream[None]] | None = None  # gate -> its lane's stream

    def _open(self) -> None:
        gates = list(self.backends)
        for g in gates:
            self.wanted.setdefault(g, [])
            self.seconds.setdefault(g, [])
        n = max(1, min(self.threads, len(gates)))
        if n == 1:
            self._inline = _Lane(dict(self.backends), self.wanted, self.seconds)
            return
        self._lanes = {}
        for i in range(n):
            mine = {g: self.backends[g] for g in gates[i::n]}
            # deep queues: a lane may run far ahead of a slower one (steps are small)
            stream: ThreadStream[None] = ThreadStream(
                _Lane(mine, self.wanted, self.seconds),
                "scanguard-instances-" + "+".join(mine),
                batch=4,
                pending=64,
            )
            self._lanes.update(dict.fromkeys(mine, stream))

    def feed(self, items: list[DetachedStep]) -> None:
        """One batch: the calls the loop makes, each instance's in their order."""
        if self._inline is None and self._lanes is None:
            self._open()
        if self._inline is not None:
            self._inline.feed(items)
            return
        assert self._lanes is not None
        for item in items:
            self._lanes[item.gate].put(item)

    def _streams(self) -> list[ThreadStream[None]]:
        unique = {} if self._lanes is None else {id(s): s for s in self._lanes.values()}
        return list(unique.values())

    def finish(self) -> dict[str, DetachedResult]:
        """Every instance's `DetachedResult` (after every lane's last step)."""
        try:
            for stream in self._streams():
                stream.result()
        finally:
            self.abort()
        return {
            g: DetachedResult(
                np.array(self.wanted.get(g, []), dtype=bool),
                np.array(self.seconds.get(g, []), dtype=np.float64),
                FinishedBackend.of(b) if self.snapshot else None,
            )
            for g, b in self.backends.items()
        }

    def abort(self) -> None:
        """Stop the lanes' threads (a failed run; `finish` ends them too)."""
        for stream in self._streams():
            stream.abort()
        self._lanes = None


class DetachedGroup:
    """The worker of some instances, seen from the loop's process.

    Args:
        spec: Its instances.
    """

    def __init__(self, spec: InstancesSpec) -> None:
        # 16 scans per batch: the worker's instances wait for each other once per batch, and
        # a loop search of one (tens of ms) is then spread over many scans of the other
        stream = ProcessStream(
            spec, "comparison instances " + "+".join(spec.gates), batch=16 * len(spec.gates)
        )
        self._start(spec.gates, spec.config.backend, stream)

    def _start(
        self,
        gates: tuple[str, ...],
        backend_name: str,
        stream: ProcessStream[dict[str, DetachedResult]] | ThreadStream[dict[str, DetachedResult]],
    ) -> None:
        self.gates = gates
        self.backend_name = backend_name
        self._stream = stream
        self._results: dict[str, DetachedResult] | None = None

    @classmethod
    def on_thread(cls, backends: dict[str, Backend], config: RunConfig) -> DetachedGroup:
        """The instances ``backends`` of the loop's own process, updated on a thread of theirs.

        They update side by side as in the loop (`RunConfig.instance_workers`), a batch of
        scans at a time, and stay in their place when the recording ends.
        """
        gates = tuple(backends)
        handler = InstancesHandler(
            dict(backends), threads=config.instance_workers(len(gates)), snapshot=False
        )
        stream = ThreadStream(
            handler, "back-end instances " + "+".join(gates), batch=8 * len(gates)
        )
        group = cls.__new__(cls)
        group._start(gates, config.backend, stream)
        return group

    def submit(self, step: DetachedStep) -> None:
        """Hand one instance's scan to the worker (returns at once)."""
        self._stream.put(step)

    def result(self, gate: str) -> DetachedResult:
        """The instance's result (the first call waits for the worker to finish them all).

        Raises:
            scanguard.runtime.streaming.StreamError: The worker failed or died.
        """
        if self._results is None:
            self._results = self._stream.result(self._progress)
        return self._results[gate]

    def _progress(self, fed: int, sent: int) -> None:
        n = max(len(self.gates), 1)
        logger.info(
            "%s: scans %d/%d (%d %%)",
            self._stream.name,
            fed // n,
            sent // n,
            100 * fed // max(sent, 1),
        )

    def abort(self) -> None:
        """Stop the worker (the run failed)."""
        if self._results is None:
            self._stream.abort()


class DetachedBackend:
    """One instance of a `DetachedGroup`: the loop submits its scans; `result` ends it.

    It is a `Backend` by name only: the loop never asks it ``wants_scan`` or gives it an
    ``update`` (they raise), and replaces it with its `FinishedBackend` when the recording
    ends.
    """

    def __init__(self, group: DetachedGroup, gate: str) -> None:
        self.group = group
        self.gate = gate

    @property
    def name(self) -> str:
        """The back end's name."""
        return self.group.backend_name

    def submit(
        self,
        scan: LaserScan,
        odometry: NDArray[np.float64],
        *,
        usable: bool,
        match: NDArray[np.float64] | None,
        covariance: NDArray[np.float64] | None,
    ) -> None:
        """Hand the worker this instance's scan (see `DetachedStep`)."""
        self.group.submit(DetachedStep(self.gate, scan, odometry, usable, match, covariance))

    def result(self) -> DetachedResult:
        """Wait for the worker; this instance's `DetachedResult`."""
        return self.group.result(self.gate)

    def abort(self) -> None:
        """Stop the worker (the run failed)."""
        self.group.abort()

    def _elsewhere(self, *_: Any, **__: Any) -> Any:
        raise BackendError(f"the {self.gate!r} instance runs in a worker process")

    wants_scan = update = trajectory = used = grid = _elsewhere

    @property
    def pose(self) -> NDArray[np.float64]:
        """Refused: the instance runs in a worker process."""
        out: NDArray[np.float64] = self._elsewhere()
        return out
