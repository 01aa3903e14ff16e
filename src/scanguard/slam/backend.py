"""The `Backend` protocol: what the guarded loop hands a SLAM back end, and what it reads back.

The judge (`scanguard.slam.judge.Judge`) judges each scan's match to the previous scan and a
gate (`scanguard.slam.gate.Gate`) turns the verdict into accept or reject; a back end owns the
state estimate (poses and map). Per scan the loop:

1. asks ``backend.wants_scan(stamp, odometry)`` whether the back end would use this scan now
   (GMapping only processes a scan after ``linearUpdate`` / ``angularUpdate`` /
   ``temporalUpdate``; the judge's cost is only paid for those scans);
2. calls ``backend.update(scan, odometry, usable=..., match=...)``. ``usable=False`` means the
   guard rejected the scan: the back end moves by odometry (its motion model) only and does
   not integrate the scan into any map;
3. at the end reads ``trajectory()`` (one pose per scan it was given), ``grid()`` (the map of
   its best estimate) and ``used()`` (which scans went into that map).

`FrontendBackend` (``frontend``) is the simplest back end: it chains the guard's scan-to-scan
matches (odometry or a motion prior where a match is rejected); `scanguard.slam.stream.ScanGuard`
streams scans through it.
The GMapping particle filter lives in `scanguard.slam.gmapping`.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import ConfigError
from scanguard.geometry import as_pose, compose, relative
from scanguard.scan import LaserScan
from scanguard.slam.grid import GridConfig, OccupancyGrid, sensor_to_robot_increment

logger = logging.getLogger(__name__)


def finite_odometry(odometry: ArrayLike | None) -> NDArray[np.float64] | None:
    """The odometry pose ``(3,)``, or None when there is none or it is not finite."""
    if odometry is None:
        return None
    o = as_pose(odometry).reshape(3).astype(np.float64)
    return o if bool(np.all(np.isfinite(o))) else None


def checked_odometry(
    odometry: ArrayLike | None,
    last: NDArray[np.float64] | None,
    index: int,
    nonfinite: int,
) -> tuple[NDArray[np.float64], int]:
    """The odometry pose a back end uses for scan ``index``, as every back end treats it.

    A non-finite pose counts as missing (warned about once, counted); a missing pose repeats
    ``last`` (zero motion), or is the origin before any pose.

    Args:
        odometry: The pose given with the scan (or None).
        last: The last pose used (None before the first).
        index: Index of the scan (for the warning).
        nonfinite: Non-finite poses seen so far.

    Returns:
        The pose to use, and the updated count of non-finite poses.
    """
    odom = finite_odometry(odometry)
    if odometry is not None and odom is None:
        if nonfinite == 0:
            logger.warning(
                "non-finite odometry pose at scan %d: treated as missing (zero motion)", index
            )
        nonfinite += 1
    if odom is None:
        odom = last.copy() if last is not None else np.zeros(3)
    return odom, nonfinite


@runtime_checkable
class Backend(Protocol):
    """A SLAM back end driven one scan at a time."""

    @property
    def name(self) -> str:
        """Short name (``frontend``, ``gmapping``...)."""
        ...

    def wants_scan(self, stamp: float, odometry: NDArray[np.float64] | None) -> bool:
        """Whether `update` with this scan would use it (so the loop should judge it)."""
        ...

    def update(
        self,
        scan: LaserScan,
        odometry: NDArray[np.float64] | None,
        *,
        usable: bool = True,
        match: NDArray[np.float64] | None = None,
    ) -> None:
        """Feed the next scan.

        Args:
            scan: The new scan.
            odometry: Robot odometry pose ``(x, y, theta)`` at ``scan.stamp`` (absolute; only
                increments are used), or None when the recording has none.
            usable: False when the guard rejected the scan: move by odometry only, and do not
                integrate the scan into any map.
            match: The guard's match of this scan in the previous scan's sensor frame, when it
                computed one (a scan-to-scan back end chains it; others may ignore it).
        """
        ...

    @property
    def pose(self) -> NDArray[np.float64]:
        """Current best robot pose ``(x, y, theta)``."""
        ...

    def trajectory(self) -> NDArray[np.float64]:
        """Best robot pose at every scan given so far, shape ``(N, 3)``."""
        ...

    def used(self) -> NDArray[np.bool_]:
        """Per scan given so far: whether it went into the best estimate's map."""
        ...

    def grid(self) -> Any:
        """The best estimate's occupancy grid (`scanguard.slam.grid.OccupancyGrid`)."""
        ...


@dataclass
class FinishedBackend:
    """A back end's results once its recording is over: the read side of `Backend`, picklable.

    What a back end that ran in a process of its own sends back
    (`scanguard.slam.detached`): the values of `trajectory`, `used`, `grid`, `pose` and the
    ``stats`` it had when the recording ended, without its solver or particles. It takes no
    more scans.

    Attributes:
        name: The back end's name.
        final_pose: Its `pose` at the end.
        poses: Its `trajectory` ``(N, 3)``.
        used_mask: Its `used` ``(N,)``.
        final_grid: Its `grid` (None where the caller builds the map from the trajectory).
        stats: Its counters and timings (``stats``), when it keeps them.
    """

    name: str
    final_pose: NDArray[np.float64]
    poses: NDArray[np.float64]
    used_mask: NDArray[np.bool_]
    final_grid: Any
    stats: dict[str, float] = field(default_factory=dict)

    @classmethod
    def of(cls, backend: Backend) -> FinishedBackend:
        """``backend``'s results as they are now (its own ``snapshot()`` where it has one)."""
        snapshot = getattr(backend, "snapshot", None)
        if snapshot is not None:
            out: FinishedBackend = snapshot()
            return out
        poses = np.asarray(backend.trajectory(), dtype=np.float64).reshape(-1, 3)
        return cls(
            name=backend.name,
            final_pose=np.asarray(backend.pose, dtype=np.float64).reshape(3).copy(),
            poses=poses,
            used_mask=np.asarray(backend.used(), dtype=bool),
            final_grid=backend.grid(),
            stats=dict(getattr(backend, "stats", None) or {}),
        )

    def wants_scan(self, stamp: float, odometry: NDArray[np.float64] | None) -> bool:
        """False: the recording is over."""
        return False

    def update(
        self,
        scan: LaserScan,
        odometry: NDArray[np.float64] | None,
        *,
        usable: bool = True,
        match: NDArray[np.float64] | None = None,
    ) -> None:
        """Refused: a finished back end takes no more scans.

        Raises:
            ConfigError: Always.
        """
        raise ConfigError(f"back end {self.name!r} has finished its recording: no more scans")

    @property
    def pose(self) -> NDArray[np.float64]:
        """The robot pose at the end."""
        return self.final_pose.copy()

    def trajectory(self) -> NDArray[np.float64]:
        """The robot pose at every scan."""
        return self.poses.copy()

    def used(self) -> NDArray[np.bool_]:
        """Per scan: whether it went into the map."""
        return self.used_mask.copy()

    def grid(self) -> Any:
        """The final map (None: build it from `trajectory` and `used`)."""
        return self.final_grid


MotionPrior = Literal["constant_position", "constant_velocity"]
#: Motions on a step without a usable match and without odometry (`FrontendBackend`).
MOTION_PRIORS: tuple[str, ...] = ("constant_position", "constant_velocity")


def _timed_insert(grid: OccupancyGrid, scan: LaserScan, laser_pose: NDArray[np.float64]) -> float:
    t = time.perf_counter()
    grid.insert(scan, laser_pose)
    return time.perf_counter() - t


class FrontendBackend:
    """The scan-to-scan chain as a back end (``frontend``): the loop's historical "SLAM".

    Each scan's pose is the previous pose composed with one robot-frame increment:

    * the guard's match (converted from the sensor frame with the laser offset) when the scan
      is ``usable`` and the match is finite;
    * otherwise the odometry increment since the previous scan;
    * without odometry, the motion prior: ``constant_position`` (stay: the safest guess for a
      hand-held or slow sensor) or ``constant_velocity`` (repeat the last applied increment).

    Scans whose match was applied (and the first scan, when usable) are inserted into an
    `OccupancyGrid` at the chained pose; with ``map_in_background`` on a worker thread (the
    numba ray tracer releases the GIL), so the map update leaves the per-scan critical path.
    The grid is the same (inserts keep their order); `grid` waits for pending inserts.

    Args:
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose of the first scan.
        motion_prior: Motion on a step without a usable match and without odometry.
        grid: Occupancy grid settings (defaults if None).
        update_map: Keep the occupancy grid (off: `grid` returns None).
        map_in_background: Insert scans into the grid on a worker thread.
    """

    def __init__(
        self,
        *,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
        initial_pose: ArrayLike = (0.0, 0.0, 0.0),
        motion_prior: MotionPrior = "constant_position",
        grid: GridConfig | None = None,
        update_map: bool = True,
        map_in_background: bool = False,
    ) -> None:
        if motion_prior not in MOTION_PRIORS:
            raise ConfigError(
                f"unknown motion prior {motion_prior!r}: use constant_position or constant_velocity"
            )
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self.motion_prior = motion_prior
        self.map_in_background = map_in_background
        self._pose = as_pose(initial_pose).reshape(3).copy()
        self._poses: list[NDArray[np.float64]] = []
        self._used: list[bool] = []
        self._prev_odom: NDArray[np.float64] | None = None
        #: The robot-frame increment applied by the last `update` (zero after the first).
        self.increment = np.zeros(3)
        self._grid: OccupancyGrid | None = None
        if update_map:
            p0 = self._pose
            self._grid = OccupancyGrid(grid, origin=(float(p0[0]) - 10.0, float(p0[1]) - 10.0))
        self._map_worker: ThreadPoolExecutor | None = None
        self._map_jobs: list[Future[float]] = []
        #: Seconds spent by each background map insert (``map_in_background`` only).
        self.background_map_seconds: list[float] = []

    @property
    def name(self) -> str:
        """``frontend``."""
        return "frontend"

    def wants_scan(self, stamp: float, odometry: NDArray[np.float64] | None) -> bool:
        """Always True: every scan is chained."""
        return True

    def _increment(
        self, odom: NDArray[np.float64] | None, match: NDArray[np.float64] | None
    ) -> NDArray[np.float64]:
        """The match when given, else the odometry increment, else the motion prior."""
        if match is not None:
            return sensor_to_robot_increment(match.reshape(3), self.laser_offset)
        if odom is not None and self._prev_odom is not None:
            return relative(self._prev_odom, odom)
        if self.motion_prior == "constant_velocity":
            return self.increment.copy()
        return np.zeros(3)

    def update(
        self,
        scan: LaserScan,
        odometry: NDArray[np.float64] | None,
        *,
        usable: bool = True,
        match: NDArray[np.float64] | None = None,
    ) -> None:
        """Chain the next scan (see the class docstring for the increment chosen).

        Args:
            scan: The new scan.
            odometry: Robot odometry pose at ``scan.stamp`` (absolute), or None.
            usable: False when the guard rejected the scan.
            match: Sensor-frame pose of this scan in the previous scan's sensor frame.
        """
        odom = None if odometry is None else as_pose(odometry).reshape(3).copy()
        if not self._poses:
            used = bool(usable)
        else:
            m = None if match is None else np.asarray(match, dtype=np.float64)
            used = bool(usable and m is not None and np.all(np.isfinite(m)))
            applied = self._increment(odom, m if used else None)
            self._pose = compose(self._pose, applied)
            self.increment = np.asarray(applied, dtype=np.float64).copy()
        if used:
            self._insert(scan)
        self._prev_odom = odom
        self._poses.append(self._pose.copy())
        self._used.append(used)

    def _insert(self, scan: LaserScan) -> None:
        grid = self._grid
        if grid is None:
            return
        laser_pose = compose(self._pose, self.laser_offset)
        if self.map_in_background:
            if self._map_worker is None:
                self._map_worker = ThreadPoolExecutor(1, thread_name_prefix="scanguard-map")
            self._map_jobs.append(self._map_worker.submit(_timed_insert, grid, scan, laser_pose))
        else:
            grid.insert(scan, laser_pose)

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

    @property
    def pose(self) -> NDArray[np.float64]:
        """Current robot pose ``(x, y, theta)``."""
        return self._pose.copy()

    def trajectory(self) -> NDArray[np.float64]:
        """Robot pose at every scan given so far, ``(N, 3)``."""
        if not self._poses:
            return np.zeros((0, 3))
        return np.array(self._poses, dtype=np.float64)

    def used(self) -> NDArray[np.bool_]:
        """Per scan: whether it was inserted into the map (match applied, or the first scan)."""
        return np.array(self._used, dtype=bool)

    def grid(self) -> OccupancyGrid | None:
        """The occupancy grid of used scans (None with ``update_map=False``); up to date."""
        self.flush()
        return self._grid

    def __repr__(self) -> str:
        return f"FrontendBackend(motion_prior={self.motion_prior!r}, scans={len(self._poses)})"
