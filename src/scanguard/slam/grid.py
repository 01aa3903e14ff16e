"""SLAM front end pieces: pose fusion, a log-odds occupancy grid and map/trajectory export.

The grid follows the paper's Figure 3: only scans whose match was accepted are inserted, so a
faulty match can never smear moving people or a mis-aligned wall into the map.

Map files follow ROS ``map_server`` conventions (``map_saver`` defaults): a binary PGM where
occupied = 0, free = 254 and unknown = 205, plus a YAML with ``resolution``, ``origin`` (world
pose of the lower-left corner of the lower-left pixel), ``negate: 0``, ``occupied_thresh: 0.65``
and ``free_thresh: 0.196``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numba
import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from scanguard.config import YamlModel
from scanguard.errors import ConfigError, InputError
from scanguard.fsutil import atomic_path, atomic_write_bytes, atomic_write_text, save_figure
from scanguard.geometry import as_pose, compose, inverse
from scanguard.scan import LaserScan

logger = logging.getLogger(__name__)

#: PGM pixel values written by ROS ``map_saver`` (trinary mode).
PGM_OCCUPIED = 0
PGM_FREE = 254
PGM_UNKNOWN = 205


class GridConfig(YamlModel):
    """Occupancy grid settings.

    Attributes:
        resolution: Cell size (m), at most 10.
        l_occ: Log-odds added to a cell that ends a beam.
        l_free: Log-odds added to a cell a beam passes through (negative).
        l_min: Lower clamp of the log-odds (keeps cells able to change their mind), < 0:
            l_min >= l_max would invert the map.
        l_max: Upper clamp of the log-odds, > 0.
        occupied_thresh: Probability above which a cell is exported as occupied.
        free_thresh: Probability below which a cell is exported as free.
        max_range: Beams longer than this are cut (m); their cut end is not marked occupied.
        trace_no_return: Trace free space along beams without a return, up to ``max_range``.
        grow_margin: Extra room (m) added on each side when the grid has to grow.
    """

    resolution: float = Field(default=0.05, gt=0.0, le=10.0)
    l_occ: float = Field(default=0.85, gt=0.0)
    l_free: float = Field(default=-0.4, lt=0.0)
    l_min: float = Field(default=-4.0, lt=0.0, ge=-1e3)
    l_max: float = Field(default=4.0, gt=0.0, le=1e3)
    occupied_thresh: float = Field(default=0.65, gt=0.0, lt=1.0)
    free_thresh: float = Field(default=0.196, gt=0.0, lt=1.0)
    max_range: float = Field(default=30.0, gt=0.0, le=1000.0)
    trace_no_return: bool = False
    grow_margin: float = Field(default=5.0, ge=0.0, le=1000.0)


@numba.njit(cache=True, nogil=True)
def _trace_rays(
    logodds: NDArray[np.float32],
    stamps: NDArray[np.int32],
    scan_id: int,
    sx: float,
    sy: float,
    ex: NDArray[np.float64],
    ey: NDArray[np.float64],
    hit: NDArray[np.bool_],
    l_free: float,
    l_occ: float,
    l_min: float,
    l_max: float,
) -> None:  # pragma: no cover - compiled
    h, w = logodds.shape
    # flat views: a Bresenham step is then one index increment (+-1 or +-w)
    lo = logodds.reshape(-1)
    st = stamps.reshape(-1)
    x0 = math.floor(sx)
    y0 = math.floor(sy)
    n = ex.shape[0]
    # endpoints first, so that a free ray crossing an obstacle seen by another beam of the same
    # scan does not erase it; each cell is updated at most once per scan
    for k in range(n):
        if hit[k]:
            cx = math.floor(ex[k])
            cy = math.floor(ey[k])
            if 0 <= cx < w and 0 <= cy < h and stamps[cy, cx] != scan_id:
                stamps[cy, cx] = scan_id
                v = logodds[cy, cx] + l_occ
                logodds[cy, cx] = l_max if v > l_max else v
    if not (0 <= x0 < w and 0 <= y0 < h):
        return  # `OccupancyGrid.insert` grows the grid around the sensor first
    for k in range(n):
        x1 = math.floor(ex[k])
        y1 = math.floor(ey[k])
        if not (0 <= x1 < w and 0 <= y1 < h):
            continue  # likewise around every endpoint; never happens from `insert`
        # Both ends inside the (rectangular) grid, so is every cell between: no bounds
        # checks in the loop, and a Bresenham step is one flat index increment.
        dx = abs(x1 - x0)
        dy = -abs(y1 - y0)
        stx = 1 if x0 < x1 else -1
        err = dx + dy
        idx = y0 * w + x0
        end = y1 * w + x1
        row_step = (1 if y0 < y1 else -1) * w
        while idx != end:
            if st[idx] != scan_id:
                st[idx] = scan_id
                v = lo[idx] + l_free
                lo[idx] = l_min if v < l_min else v
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                idx += stx
            if e2 <= dx:
                err += dx
                idx += row_step
        if not hit[k] and stamps[y1, x1] != scan_id:
            stamps[y1, x1] = scan_id
            v = logodds[y1, x1] + l_free
            logodds[y1, x1] = l_min if v < l_min else v


class OccupancyGrid:
    """A growing log-odds occupancy grid with a numba Bresenham ray tracer.

    Cell ``[row, col]`` covers world ``x in origin_x + col*res + [0, res)`` and
    ``y in origin_y + row*res + [0, res)``; row 0 is the lowest ``y``.

    Args:
        config: Grid settings (defaults if None).
        origin: World ``(x, y)`` of the lower-left corner of cell ``[0, 0]``.
        shape: Initial ``(rows, cols)``; the grid grows on demand.
    """

    def __init__(
        self,
        config: GridConfig | None = None,
        origin: tuple[float, float] = (-10.0, -10.0),
        shape: tuple[int, int] = (400, 400),
    ) -> None:
        self.config = config or GridConfig()
        if self.config.free_thresh >= self.config.occupied_thresh:
            raise ConfigError(
                f"grid free_thresh {self.config.free_thresh} must be below "
                f"occupied_thresh {self.config.occupied_thresh}"
            )
        self.origin = np.array(origin, dtype=np.float64)
        self.logodds = np.zeros(shape, dtype=np.float32)
        self._stamps = np.full(shape, -1, dtype=np.int32)
        self.n_updates = 0

    @property
    def resolution(self) -> float:
        """Cell size (m)."""
        return float(self.config.resolution)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return (int(self.logodds.shape[0]), int(self.logodds.shape[1]))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` of the grid in the world (matplotlib's ``extent``)."""
        rows, cols = self.shape
        r = self.resolution
        x0, y0 = (float(v) for v in self.origin)
        return (x0, x0 + cols * r, y0, y0 + rows * r)

    def world_to_cell(self, xy: ArrayLike) -> NDArray[np.int64]:
        """Integer ``(col, row)`` cells of world points ``(N, 2)`` (may lie outside the grid)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.floor((p - self.origin) / self.resolution).astype(np.int64)

    def cell_center(self, col: int, row: int) -> tuple[float, float]:
        """World coordinates of the centre of cell ``(col, row)``."""
        r = self.resolution
        return (
            float(self.origin[0] + (col + 0.5) * r),
            float(self.origin[1] + (row + 0.5) * r),
        )

    def _ensure_contains(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> None:
        r = self.resolution
        rows, cols = self.shape
        top = self.origin + np.array([cols, rows], dtype=np.float64) * r
        if np.all(lo >= self.origin) and np.all(hi < top):
            return
        margin = self.config.grow_margin
        new_lo = np.where(lo < self.origin, lo - margin, self.origin)
        # keep cells aligned with the old lattice so existing cells are copied, not resampled
        shift = np.ceil((self.origin - new_lo) / r - 1e-9).astype(np.int64)
        new_origin = self.origin - shift * r
        new_hi = np.where(hi >= top, hi + margin, top)
        new_cols = int(np.ceil((new_hi[0] - new_origin[0]) / r - 1e-9))
        new_rows = int(np.ceil((new_hi[1] - new_origin[1]) / r - 1e-9))
        lo_new = np.zeros((new_rows, new_cols), dtype=np.float32)
        st_new = np.full((new_rows, new_cols), -1, dtype=np.int32)
        c0, r0 = int(shift[0]), int(shift[1])
        lo_new[r0 : r0 + rows, c0 : c0 + cols] = self.logodds
        st_new[r0 : r0 + rows, c0 : c0 + cols] = self._stamps
        self.logodds, self._stamps, self.origin = lo_new, st_new, new_origin
        logger.debug("grid grown to %dx%d cells, origin %s", new_rows, new_cols, new_origin)

    def insert(self, scan: LaserScan, laser_pose: ArrayLike) -> None:
        """Ray-trace one scan taken from ``laser_pose`` (pose of the sensor in the map frame).

        Args:
            scan: The scan; invalid beams are skipped unless ``trace_no_return`` is set.
            laser_pose: Sensor pose ``(x, y, theta)`` in the map frame.
        """
        pose = as_pose(laser_pose).reshape(3)
        cfg = self.config
        r = scan.ranges.astype(np.float64)
        valid = scan.valid
        hit = valid & (r <= cfg.max_range)
        use = hit.copy()
        dist = np.where(hit, r, cfg.max_range)
        if cfg.trace_no_return:
            # only beams that saw nothing (inf / beyond range_max), not NaN or too-close errors
            with np.errstate(invalid="ignore"):
                no_return = ~valid & ((r > scan.range_max) | np.isposinf(r))
            use |= no_return | (valid & ~hit)
        ang = scan.angles[use] + pose[2]
        d = dist[use]
        wx = pose[0] + d * np.cos(ang)
        wy = pose[1] + d * np.sin(ang)
        if wx.size:
            lo = np.array([min(wx.min(), pose[0]), min(wy.min(), pose[1])])
            hi = np.array([max(wx.max(), pose[0]), max(wy.max(), pose[1])])
        else:
            lo = hi = pose[:2].copy()
        self._ensure_contains(lo, hi)
        res = self.resolution
        self.n_updates += 1
        _trace_rays(
            self.logodds,
            self._stamps,
            self.n_updates,
            (pose[0] - self.origin[0]) / res,
            (pose[1] - self.origin[1]) / res,
            (wx - self.origin[0]) / res,
            (wy - self.origin[1]) / res,
            np.ascontiguousarray(hit[use]),
            cfg.l_free,
            cfg.l_occ,
            cfg.l_min,
            cfg.l_max,
        )

    def probability(self) -> NDArray[np.float32]:
        """Occupancy probability per cell (0.5 = unknown), same layout as ``logodds``."""
        return (1.0 - 1.0 / (1.0 + np.exp(self.logodds))).astype(np.float32)

    def known_mask(self) -> NDArray[np.bool_]:
        """Cells that any beam has touched."""
        return np.asarray(self.logodds != 0.0)

    def to_image(self) -> NDArray[np.uint8]:
        """Trinary ``map_saver`` image, top row = largest ``y`` (ready to write as PGM/PNG)."""
        p = self.probability()
        img = np.full(p.shape, PGM_UNKNOWN, dtype=np.uint8)
        img[p > self.config.occupied_thresh] = PGM_OCCUPIED
        img[p < self.config.free_thresh] = PGM_FREE
        return np.ascontiguousarray(img[::-1])

    def map_server_yaml(self, image_name: str) -> dict[str, Any]:
        """The ``map_server`` YAML fields for this grid."""
        return {
            "image": image_name,
            "mode": "trinary",
            "resolution": self.resolution,
            "origin": [float(self.origin[0]), float(self.origin[1]), 0.0],
            "negate": 0,
            "occupied_thresh": float(self.config.occupied_thresh),
            "free_thresh": float(self.config.free_thresh),
        }

    def save_map_server(self, path: str | Path) -> tuple[Path, Path]:
        """Write ``<path>.pgm`` and ``<path>.yaml`` (a ROS ``map_server`` pair), atomically.

        Args:
            path: Output path; any suffix is replaced.

        Returns:
            The PGM and YAML paths.
        """
        base = Path(path)
        pgm = base.with_suffix(".pgm")
        yml = base.with_suffix(".yaml")
        img = self.to_image()
        header = f"P5\n# CREATOR: scanguard {self.resolution:.3f} m/pix\n"
        header += f"{img.shape[1]} {img.shape[0]}\n255\n"
        atomic_write_bytes(pgm, header.encode("ascii") + img.tobytes())
        atomic_write_text(yml, yaml.safe_dump(self.map_server_yaml(pgm.name), sort_keys=False))
        return pgm, yml

    def save_png(self, path: str | Path) -> Path:
        """Write the trinary map image as a greyscale PNG, atomically."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.image as mpimg

        out = Path(path)
        with atomic_path(out) as tmp:
            mpimg.imsave(tmp, self.to_image(), cmap="gray", vmin=0, vmax=255, format="png")
        return out


def read_pgm(path: str | Path) -> NDArray[np.uint8]:
    """Read a binary (P5, 8-bit) PGM such as ``map_saver`` writes.

    Raises:
        InputError: The file is missing or not an 8-bit binary PGM.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(p, f"cannot read PGM ({exc.strerror})") from None
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.find(b"\n", pos) + 1
            if pos == 0:
                break
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos:
            break
        tokens.append(data[start:pos])
    if len(tokens) < 4 or tokens[0] != b"P5":
        raise InputError(p, "not a binary (P5) PGM")
    w, h, maxval = int(tokens[1]), int(tokens[2]), int(tokens[3])
    if maxval > 255:
        raise InputError(p, f"16-bit PGM (maxval {maxval}) is not supported")
    body = data[pos + 1 : pos + 1 + w * h]
    if len(body) != w * h:
        raise InputError(p, f"PGM truncated: {len(body)} of {w * h} pixels")
    return np.frombuffer(body, dtype=np.uint8).reshape(h, w).copy()


# --- pose fusion -------------------------------------------------------------------------------


def sensor_to_robot_increment(increment: ArrayLike, laser_offset: ArrayLike) -> NDArray[np.float64]:
    """Convert a relative pose between sensor frames into one between robot frames.

    ``robot_inc = offset ⊕ sensor_inc ⊕ offset⁻¹`` (works on ``[..., 3]`` batches).
    """
    off = as_pose(laser_offset)
    return compose(compose(off, increment), inverse(off))


def robot_to_sensor_increment(increment: ArrayLike, laser_offset: ArrayLike) -> NDArray[np.float64]:
    """Inverse of `sensor_to_robot_increment`: ``offset⁻¹ ⊕ robot_inc ⊕ offset``."""
    off = as_pose(laser_offset)
    return compose(compose(inverse(off), increment), off)


def chain(start: ArrayLike, increments: ArrayLike) -> NDArray[np.float64]:
    """Compose relative increments ``(N-1, 3)`` from ``start`` into absolute poses ``(N, 3)``."""
    inc = as_pose(increments).reshape(-1, 3)
    out = np.empty((inc.shape[0] + 1, 3), dtype=np.float64)
    out[0] = as_pose(start).reshape(3)
    for i in range(inc.shape[0]):
        out[i + 1] = compose(out[i], inc[i])
    return out


def fuse_increments(
    start: ArrayLike,
    match_increments: ArrayLike,
    fallback_increments: ArrayLike,
    accepted: ArrayLike,
) -> NDArray[np.float64]:
    """Fuse a trajectory: matched increment where accepted, fallback increment elsewhere.

    Args:
        start: First pose ``(3,)``.
        match_increments: Robot-frame match increments ``(N-1, 3)`` (rows may be NaN where
            matching failed; those steps must not be accepted).
        fallback_increments: Robot-frame odometry (or fallback) increments ``(N-1, 3)``.
        accepted: Boolean ``(N-1,)``: use the match for step ``i -> i+1``.

    Returns:
        Poses ``(N, 3)``.
    """
    m = as_pose(match_increments).reshape(-1, 3)
    f = as_pose(fallback_increments).reshape(-1, 3)
    a = np.asarray(accepted, dtype=bool).reshape(-1)
    if not (m.shape == f.shape and a.shape[0] == m.shape[0]):
        raise ValueError(
            f"increment arrays disagree: match {m.shape}, fallback {f.shape}, accepted {a.shape}"
        )
    a = a & np.all(np.isfinite(m), axis=1)
    return chain(start, np.where(a[:, None], m, f))


def build_map(
    scans: Sequence[LaserScan],
    poses: ArrayLike,
    laser_offset: ArrayLike = (0.0, 0.0, 0.0),
    include: ArrayLike | None = None,
    config: GridConfig | None = None,
) -> OccupancyGrid:
    """Build a grid from scans at robot ``poses``, inserting only scans where ``include``.

    Each scan's cached derived arrays are released once inserted (`LaserScan.release`).

    Args:
        scans: The scans.
        poses: Robot poses ``(N, 3)`` in the map frame.
        laser_offset: Pose of the laser in the robot frame.
        include: Boolean ``(N,)`` mask of scans to insert (all if None).
        config: Grid settings.

    Returns:
        The grid.
    """
    p = as_pose(poses).reshape(-1, 3)
    if p.shape[0] != len(scans):
        raise ValueError(f"{len(scans)} scans but {p.shape[0]} poses")
    inc = np.ones(len(scans), dtype=bool) if include is None else np.asarray(include, dtype=bool)
    grid = OccupancyGrid(config, origin=(float(p[0, 0]) - 10.0, float(p[0, 1]) - 10.0))
    laser = compose(p, as_pose(laser_offset))
    for i in np.flatnonzero(inc).tolist():
        grid.insert(scans[i], laser[i])
        # a whole recording's validity masks are not kept for one map (recomputed on demand)
        scans[i].release()
    return grid


def save_maps_figure(
    grids: Mapping[str, OccupancyGrid],
    path: str | Path,
    trajectories: Mapping[str, NDArray[np.float64]] | None = None,
    title: str | None = None,
) -> Path:
    """Draw grids side by side (the paper's Figure 1) with optional trajectory overlays.

    Args:
        grids: Panel title -> grid.
        path: Output PNG.
        trajectories: Panel title -> robot poses ``(N, 3)`` drawn on that panel.
        title: Figure title.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(grids)
    fig, axes = plt.subplots(1, n, figsize=(6.0 * n, 6.0), squeeze=False)
    for ax, (name, grid) in zip(axes[0], grids.items(), strict=True):
        r = grid.resolution
        known = np.argwhere(grid.known_mask())
        ax.imshow(grid.to_image(), cmap="gray", vmin=0, vmax=255, extent=grid.extent)
        if trajectories and name in trajectories:
            t = trajectories[name]
            ax.plot(t[:, 0], t[:, 1], "-", color="tab:orange", lw=1.0)
        if known.size:
            (r0, c0), (r1, c1) = known.min(axis=0), known.max(axis=0)
            ax.set_xlim(grid.origin[0] + (c0 - 5) * r, grid.origin[0] + (c1 + 6) * r)
            ax.set_ylim(grid.origin[1] + (r0 - 5) * r, grid.origin[1] + (r1 + 6) * r)
        ax.set_title(name)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
    if title:
        fig.suptitle(title)
    out = save_figure(fig, Path(path), dpi=110)
    return out
