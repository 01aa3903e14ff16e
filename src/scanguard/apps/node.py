"""A live guarded SLAM node, without its transport: queue, worker, the loop, stats, saving.

`GuardNode` is what `scanguard node` runs behind a transport (`scanguard.apps.ros1_node` for
ROS 1; a ROS 2 transport would be a sibling module of the same size). The transport hands it
scans (`GuardNode.offer`, from its subscriber callback: never blocks) and implements
`Transport`: odometry and the laser's pose from its transform tree, and the publishers.

A worker thread takes the scans from a small queue (``queue_size``, default 1: a scan that
arrives while the queue is full is dropped, logged and counted; ``wait_for_scans``: an
unbounded queue, nothing dropped, for a deterministic run of a recording) and feeds each to
the same `scanguard.slam.loop.RunLoop` step that ``scanguard run`` uses, built by the same
functions (`scanguard.apps.loop_setup`), with the main (guarded) instance alone, as
``scanguard run --no-compare``. The loop is built on the first scan, once the node knows
whether odometry comes, the laser's pose on the robot and its range. ``use_odometry: auto``
decides from the transform tree the node has listened to since it was made: odometry if
``odom -> base`` is there at the first scan, waiting at most what is left of
``odometry_timeout`` since then (and at least `ODOMETRY_GRACE`); the scans that arrive before
the first one is processed are queued, never dropped.

The map is not built on the worker: every ``map_update_interval`` s of scan time the worker
copies what the map is made of, between two scans (`scanguard.apps.loop_setup.map_source`:
cheap, GMapping's history, not its map), and a second thread builds and publishes the map
and the trajectory, so a scan's latency never includes a map update.

Parameters keep slam_gmapping's names where they mean the same (`node_settings`): every
`scanguard.slam.gmapping.GMappingConfig` field (``particles``, ``delta``, ``maxUrange``,
``linearUpdate``, ``xmin``...), ``map_update_interval``, the frames; the rest of a
`RunConfig` comes from ``config`` (a scanguard YAML file).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.loop_setup import (
    adjust_without_odometry,
    build_instances,
    map_source,
    resolve_labels,
    scan_pairs,
)
from scanguard.apps.node_stats import NodeStats
from scanguard.errors import ConfigError, ScanGuardError
from scanguard.geometry import compose, inverse
from scanguard.scan import LaserScan
from scanguard.slam.config import RunConfig
from scanguard.slam.gmapping import GMappingConfig
from scanguard.slam.guard import operating_point_detector
from scanguard.slam.judge import check_detector_matcher
from scanguard.slam.loop import LoopStep, RunLoop, instance_gates

logger = logging.getLogger(__name__)

#: Seconds without a scan after which a map that misses processed scans is published.
IDLE_MAP_SECONDS = 1.0
#: Least seconds the first scan waits for tf (odometry with ``use_odometry: auto``, else the
#: laser's pose): a recording played from its start may send its transforms a moment late.
ODOMETRY_GRACE = 0.1


@dataclass(frozen=True)
class NodeOptions:
    """How the node runs (parameters with slam_gmapping's names where it has them).

    Attributes:
        map_update_interval: Seconds of scan time between map publications (slam_gmapping's).
        base_frame: The robot's frame (slam_gmapping's).
        odom_frame: The odometry frame (slam_gmapping's).
        map_frame: The map frame (slam_gmapping's).
        transform_publish_period: Seconds between ``map -> odom`` publications (0: with each
            scan only; slam_gmapping's).
        throttle_scans: Process one scan in this many (slam_gmapping's).
        use_odometry: ``auto`` (odometry from tf if the node has it by the first scan; see
            the module docstring), ``on`` (required) or ``off``.
        odometry_timeout: Seconds to wait for the transform at a scan's stamp.
        queue_size: Scans waiting for the worker once it runs; one more is dropped (and
            counted). Until the first scan is processed nothing is dropped.
        wait_for_scans: Never drop: an unbounded queue (replaying a recording).
        status_interval: Seconds between status lines (log and ``~status``).
    """

    map_update_interval: float = 5.0
    base_frame: str = "base_link"
    odom_frame: str = "odom"
    map_frame: str = "map"
    transform_publish_period: float = 0.05
    throttle_scans: int = 1
    use_odometry: Literal["auto", "on", "off"] = "auto"
    odometry_timeout: float = 1.0
    queue_size: int = 1
    wait_for_scans: bool = False
    status_interval: float = 10.0


#: Parameter name -> type of the `NodeOptions` fields.
_OPTION_TYPES: dict[str, type] = {
    "map_update_interval": float,
    "base_frame": str,
    "odom_frame": str,
    "map_frame": str,
    "transform_publish_period": float,
    "throttle_scans": int,
    "use_odometry": str,
    "odometry_timeout": float,
    "queue_size": int,
    "wait_for_scans": bool,
    "status_interval": float,
}
#: RunConfig fields a parameter of the same name sets (the rest: the ``config`` file).
RUN_PARAMETERS = ("backend", "matcher", "motion", "prior")
#: Every parameter name the node reads (besides ``config``, ``model``, ``save_on_exit``).
PARAMETERS = (*_OPTION_TYPES, *GMappingConfig.model_fields, *RUN_PARAMETERS)


def node_settings(base: RunConfig, params: Mapping[str, Any]) -> tuple[RunConfig, NodeOptions]:
    """The run settings and node options of ``base`` with the node's parameters on top.

    Args:
        base: The settings of the ``config`` file (or the defaults).
        params: Parameter name -> value (slam_gmapping's names; see `PARAMETERS`).

    Raises:
        ConfigError: An unknown parameter, or a value the settings refuse (one line).
    """
    unknown = sorted(set(params) - set(PARAMETERS))
    if unknown:
        raise ConfigError(f"unknown node parameter(s): {', '.join(unknown)}")
    data = base.model_dump()
    for name in GMappingConfig.model_fields:
        if name in params:
            data["gmapping"][name] = params[name]
    for name in RUN_PARAMETERS:
        if name in params:
            data[name] = str(params[name]).replace("-", "_")
    data["compare"] = False  # the main (guarded) instance alone, as run --no-compare
    cfg = RunConfig.from_dict(data, source="node parameters")
    opts: dict[str, Any] = {}
    for name, kind in _OPTION_TYPES.items():
        if name not in params:
            continue
        value = params[name]
        try:
            opts[name] = _as_bool(value) if kind is bool else kind(value)
        except (TypeError, ValueError):
            raise ConfigError(
                f"node parameter {name}: {value!r} is not a {kind.__name__}"
            ) from None
    use = str(opts.get("use_odometry", "auto")).lower()
    use = {"true": "on", "false": "off", "1": "on", "0": "off"}.get(use, use)
    if use not in ("auto", "on", "off"):
        raise ConfigError(f"node parameter use_odometry must be auto, on or off, not {use!r}")
    opts["use_odometry"] = use
    out = NodeOptions(**opts)
    if out.queue_size < 1 or out.throttle_scans < 1:
        raise ConfigError("node parameters queue_size and throttle_scans must be 1 or more")
    for name in ("map_update_interval", "odometry_timeout", "transform_publish_period"):
        if not getattr(out, name) >= 0:
            raise ConfigError(f"node parameter {name} must be 0 or more")
    return cfg, out


def _as_bool(value: Any) -> bool:
    if isinstance(value, str):
        if value.lower() in ("true", "1", "yes", "on"):
            return True
        if value.lower() in ("false", "0", "no", "off"):
            return False
        raise ValueError(value)
    return bool(value)


class Transport(Protocol):
    """What a transport (ROS 1, ROS 2) gives the node and takes from it.

    Every method is called from the node's worker thread.
    """

    def odometry(self, stamp: float, timeout: float) -> NDArray[np.float64] | None:
        """Robot pose in the odometry frame at ``stamp`` (``odom -> base``), or None."""

    def laser_offset(
        self, frame_id: str, stamp: float, timeout: float
    ) -> NDArray[np.float64] | None:
        """Pose of the scan frame in the robot frame (``base -> frame_id``), or None."""

    def publish_decision(self, decision: Mapping[str, Any]) -> None:
        """The guard's decision on one scan (JSON-ready)."""

    def publish_pose(self, stamp: float, map_to_odom: NDArray[np.float64], odometry: bool) -> None:
        """The ``map -> odom`` transform (without odometry also ``odom -> base``: identity)."""

    def publish_map(self, grid: Any, stamp: float) -> None:
        """The map (`scanguard.slam.grid.OccupancyGrid`) and its metadata."""

    def publish_path(self, stamps: NDArray[np.float64], poses: NDArray[np.float64]) -> None:
        """The trajectory: robot poses ``(N, 3)`` in the map frame."""

    def publish_status(self, status: Mapping[str, Any]) -> None:
        """The node's counters and latency (see `NodeStats.summary`)."""


@dataclass(frozen=True)
class _Incoming:
    scan: LaserScan
    frame_id: str
    received: float  # time.monotonic() in the callback


class GuardNode:
    """The guarded SLAM of a live stream of scans (see the module docstring).

    Args:
        cfg: Run settings (`node_settings`).
        options: Node options.
        detector: The CNN fault detector.
        baseline: The classical detector the guard's policy may use, or None.
        transport: Odometry, transforms and publishers.
        matcher: Matcher override (default: ``cfg.matcher`` from the registry).
    """

    def __init__(
        self,
        cfg: RunConfig,
        options: NodeOptions,
        detector: Any,
        baseline: Any,
        transport: Transport,
        matcher: Any = None,
    ) -> None:
        from scanguard.matching import get_matcher

        self.cfg = cfg.model_copy(deep=True)
        self.options = options
        self.detector, self.baseline, self.transport = detector, baseline, transport
        self.matcher = matcher if matcher is not None else get_matcher(cfg.matcher)
        check_detector_matcher(detector, self.matcher, allow_other=self.cfg.allow_other_matcher)
        resolve_labels(self.cfg, detector)
        self.stats = NodeStats()
        self.error: BaseException | None = None
        self.loop: RunLoop | None = None
        self.odometry = False
        self.laser_offset = np.zeros(3)
        self.stamps: list[float] = []
        self._scans: list[LaserScan] = []  # only for a back end without its own map
        self._keeps_scans = False
        self._final: tuple[int, NDArray[np.float64], Any] | None = None  # a built map
        self._map_job: _MapJob | None = None  # the snapshot the map thread builds next
        self._map_wake = threading.Event()
        self._odom_pose = np.zeros(3)
        self._map_stamp: float | None = None
        self._map_stale = False
        self._last_done = time.monotonic()
        self._last_status = time.monotonic()
        self._last_drop_log = -np.inf
        self._busy = False  # the worker is processing a scan (set and cleared by it alone)
        self._made = time.monotonic()  # the transport listens to tf from here on
        # unbounded: `offer` drops (queue_size) once the first scan is processed
        self._queue: queue.Queue[_Incoming] = queue.Queue()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # the loop and its back end: worker vs. final results
        self._worker = threading.Thread(target=self._work, name="scanguard-node", daemon=True)
        self._mapper = threading.Thread(target=self._maps, name="scanguard-map", daemon=True)

    # --- the transport's side --------------------------------------------------------------

    def start(self) -> None:
        """Start the worker and the map threads."""
        self._worker.start()
        self._mapper.start()

    def offer(self, scan: LaserScan, frame_id: str) -> bool:
        """Enqueue a scan (the subscriber callback); never blocks. False: dropped."""
        received = time.monotonic()
        self.stats.received += 1
        if (self.stats.received - 1) % self.options.throttle_scans:
            self.stats.throttled += 1
            return False
        # one subscriber thread offers: the size cannot grow between the check and the put. A
        # scan an idle worker has not picked up yet is not waiting: without this, the second
        # of two scans that arrive together (a driver's burst) was dropped by an idle node
        waiting = self._queue.qsize() - (0 if self._busy else 1)
        full = waiting >= self.options.queue_size
        if full and self.stats.processed and not self.options.wait_for_scans:
            self.stats.dropped += 1
            if received - self._last_drop_log >= 5.0:  # at most one line per 5 s
                self._last_drop_log = received
                logger.warning(
                    "scan at %.3f dropped: the worker is busy and the queue (%d) is full "
                    "(%d dropped so far)",
                    scan.stamp,
                    self.options.queue_size,
                    self.stats.dropped,
                )
            return False
        self._queue.put_nowait(_Incoming(scan, frame_id, received))
        return True

    @property
    def running(self) -> bool:
        """The worker is alive and no error stopped it."""
        return self._worker.is_alive() and self.error is None

    def stop(self, timeout: float = 1.5) -> None:
        """Stop the worker after the scan it is on (scans still queued are not processed).

        A map being built is left to finish in its (daemon) thread, unpublished.
        """
        self._stop.set()
        self._map_wake.set()
        if self._worker.is_alive():
            self._worker.join(timeout)
        left = self._queue.qsize()
        if left:
            logger.info("%d queued scan(s) not processed at exit", left)

    # --- the worker ------------------------------------------------------------------------

    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                item = self._queue.get(timeout=0.1)
            except queue.Empty:
                self._idle()
                continue
            self._busy = True
            try:
                self._process(item)
            except ScanGuardError as exc:
                if self.loop is None:  # the loop could not be built: nothing will work
                    self.error = exc
                    return
                self.stats.failed += 1
                logger.warning("scan at %.3f not processed: %s", item.scan.stamp, exc)
            except Exception as exc:  # a bug: stop the node, the transport reports it
                logger.exception("the node's worker stopped")
                self.error = exc
                return
            finally:
                self._busy = False

    def _process(self, item: _Incoming) -> None:
        scan = item.scan
        if self.loop is None:
            self._begin(item)
        odom = None
        if self.odometry:
            odom = self.transport.odometry(scan.stamp, self.options.odometry_timeout)
            if odom is None:
                self.stats.no_odometry += 1
                logger.warning("scan at %.3f skipped: no odometry at its stamp", scan.stamp)
                return
        assert self.loop is not None
        t0 = time.monotonic()
        with self._lock:
            step = self.loop.feed(scan, odom)
            self.stats.step.append(time.monotonic() - t0)
            self.stamps.append(scan.stamp)
            if self._keeps_scans:
                self._scans.append(scan)
            if odom is not None:
                self._odom_pose = odom
            backend = self.loop.instances["cnn"].backend
            # the pose its trajectory ends in (GMapping's `pose` also carries the particles'
            # sampled motion noise since its last processed scan)
            pose = np.asarray(getattr(backend, "trajectory_pose", backend.pose), dtype=np.float64)
        self.transport.publish_pose(
            scan.stamp, compose(pose.reshape(3), inverse(self._odom_pose)), self.odometry
        )
        latency = time.monotonic() - item.received
        self.stats.latency.append(latency)
        self.stats.processed += 1
        self.transport.publish_decision(self._decision(step, latency))
        self._map_stale = True
        if (
            self._map_stamp is None
            or scan.stamp - self._map_stamp >= self.options.map_update_interval
        ):
            self._request_map(scan.stamp)
        self._last_done = time.monotonic()
        self._status()

    def _idle(self) -> None:
        """No scan waiting: publish a map that misses scans after `IDLE_MAP_SECONDS`."""
        if self._map_stale and time.monotonic() - self._last_done >= IDLE_MAP_SECONDS:
            self._request_map(self.stamps[-1])
        self._status()

    def _status(self) -> None:
        now = time.monotonic()
        if now - self._last_status >= self.options.status_interval:
            self._last_status = now
            logger.info("%s", self.stats.line())
            self.transport.publish_status(self.stats.summary())

    def _request_map(self, stamp: float) -> None:
        """Hand the map thread a snapshot (the worker, between two scans; a newer one wins)."""
        with self._lock:
            count, build = self._snapshot()
        self._map_job = _MapJob(stamp, count, build, np.asarray(self.stamps))
        self._map_wake.set()
        self._map_stamp, self._map_stale = stamp, False

    def _maps(self) -> None:
        """The map thread: build each snapshot's map and publish it with the trajectory."""
        while not self._stop.is_set():
            self._map_wake.wait()
            self._map_wake.clear()
            job, self._map_job = self._map_job, None
            if job is None or self._stop.is_set():
                continue
            try:
                trajectory, grid = job.build()
                self._final = (job.count, trajectory, grid)
                if self._stop.is_set():  # the transport may be closing
                    return
                self.transport.publish_map(grid, job.stamp)
                self.transport.publish_path(job.stamps, trajectory)
            except Exception:  # a map lost is logged; the scans go on
                logger.exception("the map at %.3f was not published", job.stamp)

    def _snapshot(self) -> tuple[int, Callable[[], tuple[NDArray[np.float64], Any]]]:
        """Scans so far and a function giving their trajectory and map (under the lock).

        The function reads copies only: it may run while the worker feeds the next scans.
        """
        assert self.loop is not None
        backend = self.loop.instances["cnn"].backend
        build = map_source(backend, self._scans, self.laser_offset, self.cfg.guard.grid)
        return len(self.stamps), build

    def _begin(self, item: _Incoming) -> None:
        """Build the loop on the first scan: odometry or not, the laser's pose, its range."""
        scan, opts = item.scan, self.options
        odom = None
        wait = opts.odometry_timeout
        if opts.use_odometry != "on":  # tf has been listened to since the node was made
            wait = min(wait, max(ODOMETRY_GRACE, self._made + wait - time.monotonic()))
        laser_wait = wait  # tf is waited for once: not again after odometry that never came
        if opts.use_odometry != "off":
            odom = self.transport.odometry(scan.stamp, wait)
            laser_wait = 0.0 if odom is None else wait
            if odom is None and opts.use_odometry == "on":
                raise ConfigError(
                    f"use_odometry on: no transform {opts.odom_frame} -> {opts.base_frame} "
                    f"within {wait:g} s of the first scan"
                )
        self.odometry = odom is not None
        offset = self.transport.laser_offset(item.frame_id, scan.stamp, laser_wait)
        if offset is None:
            logger.warning(
                "no transform %s -> %s: the laser is taken to sit at the robot's origin",
                opts.base_frame,
                item.frame_id,
            )
        self.laser_offset = np.zeros(3) if offset is None else np.asarray(offset, dtype=float)
        cfg = self.cfg
        if not self.odometry:
            logger.warning(
                "no odometry (%s -> %s): each scan moves the estimate by the judged match "
                "and a constant-velocity prediction",
                opts.odom_frame,
                opts.base_frame,
            )
            if cfg.motion != "guarded_matches":
                adjust_without_odometry("node", cfg)
        start = np.zeros(3) if odom is None else np.asarray(odom, dtype=np.float64)
        # the operating point `run` gives the same back end (adaptive: this node's own, learning)
        detector = operating_point_detector(cfg.guard, self.detector, cfg.backend)
        gates = instance_gates(cfg, ["cnn"], detector, self.baseline)
        instances = build_instances(
            cfg,
            gates,
            detector,
            laser_offset=self.laser_offset,
            start=start,
            range_max=float(scan.range_max),
        )
        pairs = scan_pairs(cfg, self.matcher, detector, self.baseline, self.laser_offset)
        self.loop = RunLoop(
            instances, pairs, cfg, odometry=[] if self.odometry else None, start=start
        )
        self.loop.begin()
        self._keeps_scans = cfg.backend == "graph"  # its grid(): None, built from the scans
        logger.info(
            "guarding %s (%s, %d particles) on the scans of frame %s, odometry %s",
            instances["cnn"].backend.name,
            cfg.matcher,
            cfg.gmapping.particles,
            item.frame_id or "?",
            "from tf" if self.odometry else "none",
        )

    def _decision(self, step: LoopStep, latency: float) -> dict[str, Any]:
        motion = step.motion
        return {
            "index": int(step.index),
            "stamp": float(step.stamp),
            "accepted": bool(step.accepted),
            "fault_probability": _finite(step.fault_probability),
            "baseline_score": _finite(step.baseline_score),
            "reason": step.reason,
            "motion_sources": None if motion is None else motion.sources,
            "wheels_flagged": None if motion is None else bool(motion.wheels_flagged),
            "latency_ms": 1e3 * latency,
            "dropped": self.stats.dropped,
        }

    # --- results ---------------------------------------------------------------------------

    def final(self) -> tuple[NDArray[np.float64], Any]:
        """The guarded instance's trajectory ``(N, 3)`` and map, as they are now."""
        if self.loop is None:
            raise ConfigError("the node has processed no scan: no map and no trajectory")
        built = self._final
        if built is not None and built[0] == len(self.stamps):
            return built[1], built[2]  # no scan since: the map just published
        with self._lock:
            count, build = self._snapshot()
        traj, grid = build()
        self._final = (count, traj, grid)
        return traj, grid

    def save(self, out: Path) -> list[Path]:
        """Write the final map (PGM, YAML, PNG), trajectory (TUM), config and node stats."""
        from scanguard.apps.run_report import strict_json
        from scanguard.config import save_config
        from scanguard.fsutil import atomic_write_text
        from scanguard.io.tum import write_tum

        trajectory, grid = self.final()
        out.mkdir(parents=True, exist_ok=True)
        files = list(grid.save_map_server(out / "map"))
        files.append(grid.save_png(out / "map.png"))
        write_tum(out / "trajectory.tum", np.asarray(self.stamps), trajectory)
        files.append(out / "trajectory.tum")
        files.append(save_config(self.cfg, out))
        summary = {**self.stats.summary(), "odometry": self.odometry}
        if self.loop is not None:
            c = self.loop.result.counts
            summary["guard"] = {"accepted": c.accepted, "rejected": c.rejected, "failed": c.failed}
        atomic_write_text(out / "node.json", strict_json(summary))
        files.append(out / "node.json")
        return files


@dataclass(frozen=True)
class _MapJob:
    stamp: float  # the map's stamp (the last scan's)
    count: int  # scans in it
    build: Callable[[], tuple[NDArray[np.float64], Any]]  # -> trajectory, map
    stamps: NDArray[np.float64]


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
