"""Back-end instances in a process of their own: a run's comparisons on the other core.

With ``motion: fused`` nothing a back-end instance receives depends on any back end's state:
per scan, the scan, the instance's own fused odometry pose and covariance, its gate's decision
and its fused step. The loop (`scanguard.slam.loop.RunLoop`) can therefore hand a comparison
instance's inputs to a worker process and go on with the next scan; the worker runs the calls
the loop would have made (``wants_scan``, ``set_motion_covariance``, ``update``), in the same
order with the same values, so its results are those of the instance run in the loop's
process, bit for bit. When the recording is over it sends back what the writers read
(`scanguard.slam.backend.FinishedBackend`), and the loop puts that in the instance's place.

The guarded instance stays in the loop's process: its gate (the adaptive operating point)
learns as the run goes, and an observer or a live node reads it every scan. The worker's
instances go through each batch of scans side by side on threads (`InstancesHandler`), so that
the worker uses both cores once the loop's process has finished its own scans.

For the same reason the instances that stay in the loop's process can update on a thread of
their own, a few scans behind the loop (`DetachedGroup.on_thread`): the loop matches and
judges the next scans meanwhile, on the other core. They are the same objects, fed the same
calls in the same order, so nothing but the time changes.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import BackendError, ConfigError
from scanguard.runtime.executor import side_by_side
from scanguard.runtime.streaming import ProcessStream, ThreadStream
from scanguard.scan import LaserScan
from scanguard.slam.backend import Backend, FinishedBackend
from scanguard.slam.config import RunConfig

logger = logging.getLogger(__name__)

#: Gates whose instances may run in a worker: their closure judges need no detector.
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


@dataclass(frozen=True)
class InstancesSpec:
    """The back ends of a worker, built there as `scanguard.slam.registry.make_backend` would.

    Attributes:
        config: The run's resolved settings.
        gates: The gates of its instances (each in `DETACHABLE`).
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
        wrong = [g for g in self.gates if g not in DETACHABLE]
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
        return InstancesHandler({g: one(g) for g in self.gates}, threads=threads)


@dataclass
class InstancesHandler:
    """Feeds each `DetachedStep` to its instance (in the worker).

    With ``threads`` above 1 the instances work through a batch side by side, each its own
    steps in order: an instance reads only its own state, the scan (whose derived arrays are
    read-only and recomputed identically) and its step's values, as on the loop's threads
    (`scanguard.slam.loop.RunLoop`), so the results are those of one after the other. The
    worker's core would otherwise idle whenever the loop's process, done with its own work,
    waits for the worker's two instances.
    """

    backends: dict[str, Backend]
    threads: int = 1
    snapshot: bool = True  # False: `finish` leaves the instances where they are (a thread's)
    wanted: dict[str, list[bool]] = field(default_factory=dict)
    seconds: dict[str, list[float]] = field(default_factory=dict)
    _last: LaserScan | None = None
    _pool: ThreadPoolExecutor | None = None

    def feed(self, items: list[DetachedStep]) -> None:
        """One batch: the calls the loop makes, each instance's in their order."""
        lanes: dict[str, list[DetachedStep]] = {}
        for item in items:
            lanes.setdefault(item.gate, []).append(item)
        if self._pool is None and self.threads > 1 and len(lanes) > 1:
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="scanguard-detached")
        if self._pool is None or len(lanes) < 2:
            for gate, steps in lanes.items():
                self._steps(gate, steps)
        else:
            side_by_side(self._pool, [partial(self._steps, g, s) for g, s in lanes.items()])
        self._release(items)

    def _steps(self, gate: str, steps: list[DetachedStep]) -> None:
        backend = self.backends[gate]
        wanted = self.wanted.setdefault(gate, [])
        seconds = self.seconds.setdefault(gate, [])
        for item in steps:
            wanted.append(bool(backend.wants_scan(item.scan.stamp, item.odometry)))
            t0 = time.perf_counter()
            if item.covariance is not None:
                setter = getattr(backend, "set_motion_covariance", None)
                if setter is not None:
                    setter(item.covariance)
            backend.update(item.scan, item.odometry, usable=item.usable, match=item.match)
            seconds.append(time.perf_counter() - t0)

    def _release(self, items: list[DetachedStep]) -> None:
        """Drop the derived arrays of the scans every instance is done with, as the loop does.

        The batch's last scan may have steps in the next batch: it goes when that one starts
        with another scan (derived arrays are recomputed if needed anyway).
        """
        for item in items:
            if self._last is not None and self._last is not item.scan:
                self._last.release()
            self._last = item.scan

    def finish(self) -> dict[str, DetachedResult]:
        """Every instance's `DetachedResult`."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        return {
            g: DetachedResult(
                np.array(self.wanted.get(g, []), dtype=bool),
                np.array(self.seconds.get(g, []), dtype=np.float64),
                FinishedBackend.of(b) if self.snapshot else None,
            )
            for g, b in self.backends.items()
        }


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
