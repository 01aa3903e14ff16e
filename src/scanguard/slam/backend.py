"""The `Backend` protocol: what the guarded loop hands a SLAM back end, and what it reads back.

The guard (`scanguard.slam.guard.ScanGuard`) judges each scan's match to the previous scan; a
back end owns the state estimate. Per scan the loop:

1. asks ``backend.wants_scan(stamp, odometry)`` whether the back end would use this scan now
   (GMapping only processes a scan after ``linearUpdate`` / ``angularUpdate`` /
   ``temporalUpdate``; the judge's cost is only paid for those scans);
2. calls ``backend.update(scan, odometry, usable=..., match=...)``. ``usable=False`` means the
   guard rejected the scan: the back end moves by odometry (its motion model) only and does
   not integrate the scan into any map;
3. at the end reads ``trajectory()`` (one pose per scan it was given), ``grid()`` (the map of
   its best estimate) and ``used()`` (which scans went into that map).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from scanguard.scan import LaserScan


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
