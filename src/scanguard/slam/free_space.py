"""Free space that recent scans saw: a point that a beam passed beyond is not a wall.

People who walk along with the robot appear at the same place in every scan: scan-to-scan
matching, and scan-to-local-map matching whose map kept their earlier positions, then pull
each match towards no motion relative to them (the simulated ``crowd_follow`` and
``mixed_loop`` scenes, where the fused default drifted by metres). A beam of another scan
that reached beyond such a point proves it was not there then: the point moved. An occupancy
grid does the same by ray casting (GMapping's maps clear walkers); this is its cheap, local
form, used twice:

- `FreeSpaceHistory`: the scan-to-scan matcher leaves out the points of both scans that the
  views of the last seconds saw through (`scanguard.slam.guard.ScanPairs`);
- the graph's local map drops points its newer scans saw through, and the node's scan the
  points its older scans saw through (`scanguard.slam.graph.local_map`).

The CNN still judges the whole pair: only the match leaves the moving points out.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import compose, inverse, transform_points
from scanguard.scan import LaserScan
from scanguard.slam import _free_space as _k


@dataclass(frozen=True)
class RangeView:
    """A scan's beams as seen from its sensor pose: what it proves free.

    ``ranges`` holds NaN where a beam proves nothing (no return, out of limits).
    """

    ranges: NDArray[np.float64]
    angle_min: float
    angle_increment: float

    @classmethod
    def of(cls, scan: LaserScan) -> RangeView:
        """The view of ``scan`` (beams without a valid return prove nothing)."""
        r = np.asarray(scan.ranges, dtype=np.float64)
        valid = np.isfinite(r) & (r > max(float(scan.range_min), 0.0)) & (r < scan.range_max)
        return cls(np.where(valid, r, np.nan), float(scan.angle_min), float(scan.angle_increment))

    def seen_through(
        self,
        pose: NDArray[np.float64],
        world: NDArray[np.floating],
        margin: float,
        lateral: float = 0.0,
    ) -> NDArray[np.bool_]:
        """Per world point: every beam near its bearing reaches beyond it.

        ``margin`` (m) plus 3 % of the range keeps a wall seen again at the same range, under
        a pose error of centimetres and at a grazing angle, from being carved. The beams
        tested are the one at the point's bearing and its neighbours within ``lateral`` (m)
        of it sideways, at least one on each side: a point at the edge of a door frame or a
        pillar, placed a few centimetres off by the pose, sits beside beams that pass the
        edge, and must not be taken for a person.
        """
        inv = inverse(np.asarray(pose, dtype=np.float64).reshape(3))
        pts = np.ascontiguousarray(np.asarray(world, dtype=np.float64).reshape(-1, 2))
        return _k.seen_through(
            self.ranges, self.angle_min, self.angle_increment, float(inv[0]), float(inv[1]),
            float(inv[2]), pts, float(margin), float(lateral), _MAX_HALF_WINDOW,
        )  # fmt: skip


#: The most beams on each side `RangeView.seen_through` tests (a point very close by).
_MAX_HALF_WINDOW = 24


class FreeSpaceHistory:
    """Views of the last ``horizon`` seconds at the poses of the scan-to-scan chain.

    Args:
        horizon: Seconds of views kept.
        every: Seconds between two kept views.
        margin: See `RangeView.seen_through`.
        min_age: Only views at least this old test a point: a person walking with the robot
            has moved on by then, so the older beams reach beyond where they stand now.
        lateral: See `RangeView.seen_through` (m).
    """

    def __init__(
        self, horizon: float, every: float, margin: float, min_age: float, lateral: float = 0.0
    ) -> None:
        self.horizon = horizon
        self.lateral = lateral
        self.every = every
        self.margin = margin
        self.min_age = min_age
        self._views: deque[tuple[float, NDArray[np.float64], RangeView]] = deque()

    def moving(
        self, points: NDArray[np.float64], pose: NDArray[np.float64], stamp: float
    ) -> NDArray[np.bool_]:
        """Per sensor-frame point of a scan at ``pose``: some older view saw through it."""
        gone = np.zeros(len(points), dtype=bool)
        if not self._views or not len(points):
            return gone
        world = transform_points(pose, points)
        for t, view_pose, view in self._views:
            if stamp - t >= self.min_age:
                gone |= view.seen_through(view_pose, world, self.margin, self.lateral)
        return gone

    def add(self, scan: LaserScan, pose: NDArray[np.float64]) -> None:
        """Keep the view of ``scan`` at ``pose`` if the last kept one is ``every`` old."""
        stamp = float(scan.stamp)
        if self._views and stamp - self._views[-1][0] < self.every:
            return
        self._views.append((stamp, np.asarray(pose, dtype=np.float64).copy(), RangeView.of(scan)))
        while self._views and stamp - self._views[0][0] > self.horizon:
            self._views.popleft()


def chain(pose: NDArray[np.float64], increment: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """``pose`` moved by a sensor-frame ``increment`` (None: not moved)."""
    return pose.copy() if increment is None else compose(pose, increment)


__all__ = ["FreeSpaceHistory", "RangeView", "chain"]
