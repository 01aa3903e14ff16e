"""The likelihood grid of correlative matching: a smeared lookup table of map points.

A `LikelihoodGrid` is built once from map points: every cell holds
``exp(-d^2 / 2 sigma^2)`` of the distance ``d`` to the nearest map point (0 beyond
``3 sigma``), plus max-pooled copies for branch-and-bound (`scanguard.matching.correlative`
searches it). `outline_points` fills in the surfaces between a scan's neighbouring hits before
a map is built from them. See ``docs/matching.md``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

import scanguard.matching._correlative as _k
from scanguard.errors import MatchingError
from scanguard.io.base import MAX_COORDINATE
from scanguard.matching.config import CorrelativeConfig
from scanguard.matching.icp import PointsLike, as_points

#: Smearing is truncated at this many sigmas (the table is 0 beyond).
CUTOFF_SIGMAS = 3.0


#: Refused: a pyramid with more cells than this (all levels), about 1.6 GB of float32.
MAX_CELLS = 400_000_000


class LikelihoodGrid:
    """Likelihood lookup table built once from map points, with its max-pooled pyramid.

    Attributes:
        points: The map points ``(N, 2)`` it was built from (for the ICP refinement).
        config: The config it was built with (resolution, sigma and levels are fixed here).
        resolution: Cell size (m).
        origin: ``(x0, y0)``, the lower-left corner of cell ``(0, 0)`` in the map frame.
        levels: Number of pyramid levels.
    """

    def __init__(
        self,
        points: NDArray[np.float64],
        config: CorrelativeConfig,
        origin: tuple[float, float],
        stack: NDArray[np.float32],
    ) -> None:
        """Wrap prepared arrays; use `from_points` to build one."""
        self.points = points
        self.config = config
        self.resolution = float(config.resolution)
        self.origin = origin
        self.levels = int(stack.shape[0])
        self.pad = (1 << (self.levels - 1)) - 1
        self._stack = stack

    @classmethod
    def from_points(
        cls, points: PointsLike, config: CorrelativeConfig, *, margin: float | None = None
    ) -> LikelihoodGrid:
        """Build the table (and pyramid) of map points given in the map frame.

        Args:
            points: Map points ``(N, 2)`` (or a `LaserScan`); non-finite rows are dropped.
            config: Resolution, sigma and levels are taken from it.
            margin: Extra border (m) around the points' bounding box; None = the smearing
                cutoff (``3 sigma``) plus one cell, beyond which the table would be 0 anyway.

        Raises:
            MatchingError: No finite point, a negative margin, or a grid too large
                (``MAX_CELLS``; usually a far outlier point).
        """
        pts = as_points(points, "map points")
        if pts.shape[0] == 0:
            raise MatchingError("map points: no finite point to build a likelihood grid from")
        r = float(config.resolution)
        cutoff = CUTOFF_SIGMAS * float(config.sigma)
        m = cutoff + r if margin is None else float(margin)
        if not (math.isfinite(m) and m >= 0):
            raise MatchingError(f"margin must be finite and >= 0, got {margin}")
        xmin, ymin, xmax, ymax = _k.bounds(pts)
        lo = (xmin - m, ymin - m)
        hi = (xmax + m, ymax + m)
        nx = math.ceil((hi[0] - lo[0]) / r) + 1
        ny = math.ceil((hi[1] - lo[1]) / r) + 1
        pad = (1 << (config.levels - 1)) - 1
        cells = config.levels * (nx + pad) * (ny + pad)
        if cells > MAX_CELLS:
            raise MatchingError(
                f"likelihood grid too large: {nx} x {ny} cells x {config.levels} levels at "
                f"{r} m (map extent {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} m); "
                "check the map points for outliers or use a coarser resolution"
            )
        x0, y0 = float(lo[0]), float(lo[1])
        stack = _k.likelihood_stack(
            pts, x0, y0, r, nx, ny, float(config.sigma), cutoff, int(config.levels)
        )
        return cls(pts, config, (x0, y0), stack)

    @property
    def stack(self) -> NDArray[np.float32]:
        """The padded pyramid ``(levels, ny + pad, nx + pad)`` the search kernels read."""
        return self._stack

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)`` of the finest table."""
        return (self._stack.shape[1] - self.pad, self._stack.shape[2] - self.pad)

    @property
    def table(self) -> NDArray[np.float32]:
        """The finest table ``(ny, nx)``, values in ``[0, 1]`` (a read-only view)."""
        view = self._stack[0, self.pad :, self.pad :]
        view.flags.writeable = False
        return view

    def level(self, h: int) -> NDArray[np.float32]:
        """Level ``h`` of the pyramid (a read-only view).

        ``level(h)[j + pad, i + pad]`` is the max of the ``2**h x 2**h`` finest cells from
        ``(j, i)`` up; cells off the table count as 0.
        """
        if not 0 <= h < self.levels:
            raise MatchingError(f"level must be in 0..{self.levels - 1}, got {h}")
        view = self._stack[h]
        view.flags.writeable = False
        return view

    def score(self, source_points: PointsLike, pose: ArrayLike) -> float:
        """Mean table value (0..1) of the source points transformed by ``pose``.

        Points off the table count as 0, like in the search.

        Raises:
            MatchingError: No finite source point, or a pose that is not 3 finite numbers.
        """
        src = source_array(source_points, None)
        p = pose_array(pose, "pose")
        x0, y0 = self.origin
        total = _k.score_pose(
            self._stack[0, self.pad :, self.pad :], src, p[0], p[1], p[2], x0, y0,
            self.resolution,
        )  # fmt: skip
        return float(total) / src.shape[0]

    def __repr__(self) -> str:
        ny, nx = self.shape
        return (
            f"LikelihoodGrid({nx}x{ny} cells at {self.resolution} m, {self.levels} levels, "
            f"{self.points.shape[0]} points)"
        )


def outline_points(
    points: PointsLike,
    angle_increment: float,
    *,
    spacing: float,
    max_gap: float = 0.5,
    gap_beams: float = 10.0,
) -> NDArray[np.float64]:
    """A scan's points (in beam order) with the surfaces between neighbours filled in.

    A likelihood table built from bare beam hits favours the wrong pose when the robot drives
    along a wall at a steady heading: the new scan's wall hits then sit exactly where the old
    scan's hits were at *zero* motion, and between them at the true motion. Filling the gaps
    between neighbouring hits (the surface they sampled) makes a wall a line, so that only
    structure across the motion decides. Neighbours are joined when they are closer than
    ``min(max_gap, gap_beams * range * angle_increment)``: the spacing of hits on a wall seen
    at a shallow angle, but not the jump across an occlusion edge.

    Args:
        points: ``(N, 2)`` hits in beam order (as `LaserScan.points` gives them).
        angle_increment: Angle between beams (rad).
        spacing: Spacing of the filled-in points (m; about the grid's resolution).
        max_gap: Never join hits farther apart than this (m).
        gap_beams: Join hits closer than this many beam spacings at their range.

    Returns:
        ``(M, 2)`` points, ``M >= N``: the hits and the filled-in points.
    """
    p = as_points(points)
    if len(p) < 2 or spacing <= 0:
        return p
    return _k.outline(p, float(spacing), float(max_gap), float(gap_beams), abs(angle_increment))


def thin_points(points: NDArray[np.float64], cell: float) -> NDArray[np.float64]:
    """The first of ``points`` in each ``cell`` x ``cell`` square of the map frame's lattice.

    A local map stacks the scans of the last few nodes, a few centimetres of travel apart:
    each wall is there a dozen times over, and the likelihood grid and the ICP refinement
    paid for every copy. The points kept are the earliest in order (a local map lists its
    newest node first) and every point dropped lies within ``cell * sqrt(2)`` of one kept.

    Args:
        points: ``(N, 2)`` finite points.
        cell: Lattice spacing (m); ``<= 0`` keeps every point.

    Returns:
        The kept points, in their order (``points`` itself when nothing is dropped).
    """
    if cell <= 0 or len(points) < 2:
        return points
    keep = _k.thin(np.ascontiguousarray(points, dtype=np.float64), float(cell))
    return points if len(keep) == len(points) else points[keep]


def source_array(points: PointsLike, max_range: float | None) -> NDArray[np.float64]:
    """Finite source points within ``max_range`` of the sensor (contiguous ``(N, 2)``).

    Raises:
        MatchingError: No such point.
    """
    src = as_points(points, "source points")
    if max_range is not None and src.shape[0]:
        src = np.ascontiguousarray(src[np.hypot(src[:, 0], src[:, 1]) <= max_range])
    if src.shape[0] == 0:
        extra = "" if max_range is None else f" within max_range {max_range} m"
        raise MatchingError(f"source points: no finite point{extra} to match")
    return src


def pose_array(pose: ArrayLike, name: str) -> NDArray[np.float64]:
    """``pose`` as 3 finite floats.

    Raises:
        MatchingError: Not a pose, or not finite (the message names it ``name``).
    """
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (3,):
        raise MatchingError(f"{name} must be a pose (x, y, theta), got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise MatchingError(f"{name} must be finite, got {p.tolist()}")
    if np.abs(p[:2]).max() > MAX_COORDINATE:
        raise MatchingError(f"{name} ({p[0]:.6g}, {p[1]:.6g}) beyond +-{MAX_COORDINATE:.0e} m")
    return p


__all__ = [
    "CUTOFF_SIGMAS",
    "MAX_CELLS",
    "LikelihoodGrid",
    "outline_points",
    "pose_array",
    "source_array",
    "thin_points",
]
