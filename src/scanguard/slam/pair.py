"""A scan as the loop sees it (`Frame`) and the matching of two consecutive scans.

A match is unusable (None) when either scan has too few points, the matcher raises a
`MatchingError`, or its estimate is not finite or not ``ok``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import MatchingError
from scanguard.geometry import as_pose
from scanguard.matching.registry import Matcher
from scanguard.scan import LaserScan

logger = logging.getLogger(__name__)

Points = NDArray[np.floating[Any]]


@dataclass(frozen=True)
class Frame:
    """One scan with what is computed from it once: its points and their centroid.

    Attributes:
        scan: The raw scan.
        points: Its valid points in the sensor frame (``scan.points()``).
        mean: Their centroid (float64; NaN without points), used as current and as previous.
        odometry: The robot's absolute odometry pose at the scan, or None.
    """

    scan: LaserScan
    points: Points
    mean: NDArray[np.float64]
    odometry: NDArray[np.float64] | None = None

    @classmethod
    def of(cls, scan: LaserScan, odometry: ArrayLike | None = None) -> Frame:
        """The frame of ``scan`` (with ``odometry``, an absolute pose, or None)."""
        points = scan.points()
        mean = points.mean(axis=0, dtype=np.float64) if len(points) else np.full(2, np.nan)
        odom = None if odometry is None else as_pose(odometry).reshape(3).copy()
        return cls(scan, points, mean, odom)


def match_frames(
    matcher: Matcher | Any,
    previous: Frame,
    current: Frame,
    *,
    min_points: int,
    initial: NDArray[np.float64] | None = None,
    index: int = 0,
) -> Any:
    """Match ``current`` onto ``previous``; None when the match is unusable (module docstring).

    Args:
        matcher: Called as ``matcher(current_points, previous_points, initial)``.
        previous: The target scan.
        current: The source scan.
        min_points: A scan with fewer valid points cannot be matched.
        initial: Initial guess (sensor frame), or None (identity).
        index: Index of the current scan (for the log).
    """
    if len(current.points) < min_points or len(previous.points) < min_points:
        return None
    match: Any = None
    try:
        match = matcher(current.points, previous.points, initial)
    except MatchingError as exc:
        logger.debug("scan %d: matcher failed: %s", index, exc)
    if match is not None and not (
        np.all(np.isfinite(np.asarray(match.pose))) and getattr(match, "ok", True)
    ):
        match = None
    return match
