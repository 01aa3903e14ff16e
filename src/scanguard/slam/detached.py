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
learns as the run goes, and an observer or a live node reads it every scan.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import BackendError, ConfigError
from scanguard.runtime.streaming import ProcessStream
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
        finished: Its results (`FinishedBackend`).
    """

    wanted: NDArray[np.bool_]
    seconds: NDArray[np.float64]
    finished: FinishedBackend


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

        return InstancesHandler({g: one(g) for g in self.gates})


@dataclass
class InstancesHandler:
    """Feeds each `DetachedStep` to its instance (in the worker)."""

    backends: dict[str, Backend]
    wanted: dict[str, list[bool]] = field(default_factory=dict)
    seconds: dict[str, list[float]] = field(default_factory=dict)
    _last: LaserScan | None = None

    def feed(self, item: DetachedStep) -> None:
        """The calls the loop makes for one instance and one scan, in its order."""
        backend, scan = self.backends[item.gate], item.scan
        if self._last is not None and self._last is not scan:
            self._last.release()  # as the loop does: derived arrays are recomputed if needed
        self._last = scan
        self.wanted.setdefault(item.gate, []).append(
            bool(backend.wants_scan(scan.stamp, item.odometry))
        )
        t0 = time.perf_counter()
        if item.covariance is not None:
            setter = getattr(backend, "set_motion_covariance", None)
            if setter is not None:
                setter(item.covariance)
        backend.update(scan, item.odometry, usable=item.usable, match=item.match)
        self.seconds.setdefault(item.gate, []).append(time.perf_counter() - t0)

    def finish(self) -> dict[str, DetachedResult]:
        """Every instance's `DetachedResult`."""
        return {
            g: DetachedResult(
                np.array(self.wanted.get(g, []), dtype=bool),
                np.array(self.seconds.get(g, []), dtype=np.float64),
                FinishedBackend.of(b),
            )
            for g, b in self.backends.items()
        }


class DetachedGroup:
    """The worker of some instances, seen from the loop's process.

    Args:
        spec: Its instances.
    """

    def __init__(self, spec: InstancesSpec) -> None:
        self.gates = spec.gates
        self.backend_name = spec.config.backend
        self._stream: ProcessStream[dict[str, DetachedResult]] = ProcessStream(
            spec, "comparison instances " + "+".join(spec.gates)
        )
        self._results: dict[str, DetachedResult] | None = None

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
