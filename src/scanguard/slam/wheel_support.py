"""The wheel-support test: do a scan's own points say the last matches followed a moving thing?

A person walking just ahead of the robot along a plain corridor holds every scan-to-scan
match a little short (0.01-0.08 m a scan: below the label rule, so the CNN rightly calls each
pair normal), and over a few metres the matches lose the better part of a metre. Wheels that
spin in place give the same disagreement the other way round (the matches short of the wheels,
and right). One pair cannot tell them apart; a few scans can:

Scan ``i`` is placed on scan ``i - K`` twice, by the chain of the last ``K`` matches and by the
wheels' increment over the same scans. A point the wheels put within ``tau`` of an old point
while the matches put it more than ``3 tau`` away *supports the wheels*, and the other way round
supports the matches. Where the matches follow a person, the building's few along-corridor
edges (doors, corners) support the wheels and the person supports the matches; where the
wheels spin, the whole scene supports the matches and nothing the wheels. The test fires when
at least ``min_points`` points, and at least ``ratio`` times as many as support the matches,
support the wheels (measured on five-scan windows: README, "Twenty more office seeds").
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scanguard.geometry import compose, inverse, relative, transform_points

_Frame = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]


@dataclass(frozen=True)
class SupportCount:
    """Points of the newest scan that support the wheels over the matches, and the reverse."""

    wheels: int
    matches: int
    #: per point of the newest scan: it supports the matches (the thing they followed)
    follower: NDArray[np.bool_] | None = field(default=None, compare=False, repr=False)


class WheelSupport:
    """The last ``window`` scans' points, matches and odometry (see the module docstring).

    Args:
        laser_offset: Pose of the laser in the robot frame.
        window: Scans the newest is placed back over (K).
        tau: A point is placed right within this distance of an old point (m).
        min_points: The test fires with at least this many wheel-supporting points ...
        ratio: ... and at least this many times the match-supporting ones.
    """

    def __init__(
        self,
        laser_offset: NDArray[np.float64],
        *,
        window: int = 5,
        tau: float = 0.04,
        min_points: int = 10,
        ratio: float = 0.2,
    ) -> None:
        self.offset = np.asarray(laser_offset, dtype=np.float64).reshape(3)
        self.window = int(window)
        self.tau = float(tau)
        self.min_points = int(min_points)
        self.ratio = float(ratio)
        # (sensor-frame points, absolute robot odometry, sensor-frame match from the scan before)
        self._frames: deque[_Frame] = deque(maxlen=self.window + 1)

    def reset(self) -> None:
        """Forget every scan (a gap in the odometry or the matches)."""
        self._frames.clear()

    def push(
        self,
        points: NDArray[np.floating[Any]],
        odometry: NDArray[np.float64] | None,
        match: NDArray[np.float64] | None,
    ) -> SupportCount | None:
        """Add the newest scan (its match to the scan before, sensor frame); its count.

        None until the window holds ``window`` consecutive matches with odometry.
        """
        if odometry is None:
            self.reset()
            return None
        pts = np.asarray(points, dtype=np.float64)
        self._frames.append((pts, np.asarray(odometry, dtype=np.float64), match))
        if len(self._frames) <= self.window:
            return None
        frames = list(self._frames)
        chain = np.zeros(3)
        for _, _, m in frames[1:]:
            if m is None:
                return None
            chain = compose(chain, m)
        (old, odo_old, _), (new, odo_new, _) = frames[0], frames[-1]
        if len(old) == 0 or len(new) == 0:
            return None
        wheels = compose(compose(inverse(self.offset), relative(odo_old, odo_new)), self.offset)
        tree = cKDTree(old)
        d_w, _ = tree.query(transform_points(wheels, new))
        d_m, _ = tree.query(transform_points(chain, new))
        far = 3.0 * self.tau
        follower = (d_m < self.tau) & (d_w > far)
        return SupportCount(
            int(np.count_nonzero((d_w < self.tau) & (d_m > far))),
            int(np.count_nonzero(follower)),
            follower,
        )

    def fires(self, count: SupportCount | None) -> bool:
        """Whether ``count`` says the matches followed something the building did not."""
        return (
            count is not None
            and count.wheels >= self.min_points
            and count.wheels >= self.ratio * count.matches
        )


__all__ = ["SupportCount", "WheelSupport"]
