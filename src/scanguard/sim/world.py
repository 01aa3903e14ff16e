"""2D worlds: wall segments and round pillars with materials, plus a navigation grid.

Worlds are built by `scanguard.sim.worldgen.build_world` (built-in layouts and YAML geometry).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scanguard.errors import ConfigError
from scanguard.sim.limits import check_grid

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Material codes used by the ray caster.
MATERIALS: dict[str, int] = {"normal": 0, "glass": 1, "mirror": 2}
NORMAL, GLASS, MIRROR = 0, 1, 2

#: Most wall segments plus circles of a world (each costs ray-casting time on every scan).
MAX_PRIMITIVES = 100_000


@dataclass
class NavGrid:
    """Occupancy raster of the world: clearance (distance to the nearest surface) per cell.

    Attributes:
        origin: World coordinates of cell (0, 0)'s corner.
        resolution: Cell size (m).
        clearance: Distance (m) from each cell centre to the nearest surface, shape (H, W).
        region: Cells of the navigable interior (the connected free area holding the start).
    """

    origin: FloatArray
    resolution: float
    clearance: NDArray[np.float32]
    region: NDArray[np.bool_]

    def cells(self, xy: FloatArray) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
        """Row/column indices of points ``(N, 2)`` and a mask of those inside the grid."""
        xy = np.asarray(xy, dtype=np.float64)
        col = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.intp)
        row = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.intp)
        h, w = self.clearance.shape
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        return np.where(inside, row, 0), np.where(inside, col, 0), inside

    def clearance_at(self, xy: FloatArray) -> NDArray[np.float32]:
        """Clearance at points ``(..., 2)``; 0 outside the navigable region."""
        row, col, inside = self.cells(xy)
        ok = inside & self.region[row, col]
        return np.where(ok, self.clearance[row, col], np.float32(0.0)).astype(np.float32)

    def clearance_xy(self, x: float, y: float) -> float:
        """Clearance at one point (fast scalar path); 0 outside the navigable region."""
        col = math.floor((x - self.origin[0]) / self.resolution)
        row = math.floor((y - self.origin[1]) / self.resolution)
        h, w = self.clearance.shape
        if not (0 <= row < h and 0 <= col < w) or not self.region[row, col]:
            return 0.0
        return float(self.clearance[row, col])


@dataclass
class World:
    """Static geometry of a simulated place.

    Attributes:
        name: Scenario name.
        segments: Wall segments ``(K, 4)`` as ``(x0, y0, x1, y1)``.
        segment_material: Material code per segment ``(K,)`` (0 normal, 1 glass, 2 mirror).
        circles: Round pillars ``(C, 3)`` as ``(x, y, radius)``.
        circle_material: Material code per circle ``(C,)``.
        start: Suggested robot start pose ``(3,)``.
        nav: Navigation grid (filled by `build_world`).
        info: Free-form numbers about the layout.
        route: The generator's suggested robot route ``(K, 2)``: waypoints after the start,
            the last one back at the start (empty for generators without one).
    """

    name: str
    segments: FloatArray
    segment_material: NDArray[np.int8]
    circles: FloatArray
    circle_material: NDArray[np.int8]
    start: FloatArray
    nav: NavGrid | None = None
    info: dict[str, float] = field(default_factory=dict)
    route: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of all geometry."""
        xs = [self.segments[:, 0], self.segments[:, 2]]
        ys = [self.segments[:, 1], self.segments[:, 3]]
        if len(self.circles):
            xs += [self.circles[:, 0] - self.circles[:, 2], self.circles[:, 0] + self.circles[:, 2]]
            ys += [self.circles[:, 1] - self.circles[:, 2], self.circles[:, 1] + self.circles[:, 2]]
        x, y = np.concatenate(xs), np.concatenate(ys)
        return float(x.min()), float(y.min()), float(x.max()), float(y.max())

    def grid(self) -> NavGrid:
        """The navigation grid (raises if the world was built without one)."""
        if self.nav is None:
            raise ConfigError(f"world {self.name!r} has no navigation grid")
        return self.nav

    def is_free(self, xy: FloatArray, clearance: float) -> NDArray[np.bool_]:
        """Points ``(..., 2)`` inside the navigable region with at least ``clearance``."""
        return self.grid().clearance_at(xy) >= clearance

    def line_free(self, a: FloatArray, b: FloatArray, clearance: float) -> bool:
        """True when the straight path a→b keeps ``clearance`` everywhere (sampled finely)."""
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        n = max(2, int(np.ceil(np.hypot(*(b - a)) / (0.5 * self.grid().resolution))) + 1)
        pts = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
        return bool(np.all(self.is_free(pts, clearance)))

    def sample_free(self, rng: np.random.Generator, n: int, clearance: float) -> FloatArray:
        """``n`` random points of the navigable region with at least ``clearance``."""
        g = self.grid()
        rows, cols = np.nonzero(g.region & (g.clearance >= clearance))
        if rows.size == 0:
            raise ConfigError(f"world {self.name!r} has no free space with clearance {clearance} m")
        k = rng.integers(0, rows.size, size=n)
        jitter = rng.uniform(-0.3, 0.3, size=(n, 2)) * g.resolution
        xy = np.stack([cols[k] + 0.5, rows[k] + 0.5], axis=1) * g.resolution + g.origin + jitter
        return np.asarray(xy, dtype=np.float64)

    def free_area(self) -> float:
        """Navigable area (m²)."""
        g = self.grid()
        return float(g.region.sum()) * g.resolution**2


def nav_grid(
    segs: FloatArray,
    circles: FloatArray,
    start: FloatArray,
    res: float,
    name: str,
    other_bytes: float = 0.0,
) -> NavGrid:
    """The navigation grid of a world: clearance and the free region around ``start``.

    Raises:
        ConfigError: The start is not in free space, or its free space is not enclosed.
    """
    pts = [segs[:, :2], segs[:, 2:]]
    if len(circles):
        pts += [circles[:, :2] - circles[:, 2:3], circles[:, :2] + circles[:, 2:3]]
    allp = np.concatenate(pts)
    origin = allp.min(axis=0) - 1.0
    size = np.ceil((allp.max(axis=0) + 1.0 - origin) / res).astype(int)
    check_grid(name, (int(size[1]), int(size[0])), res, other_bytes=other_bytes)
    occ = np.zeros((int(size[1]), int(size[0])), dtype=bool)
    for x0, y0, x1, y1 in segs:
        n = int(np.ceil(math.hypot(x1 - x0, y1 - y0) / (0.25 * res))) + 1
        t = np.linspace(0.0, 1.0, n)
        c = np.floor((np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], 1) - origin) / res)
        occ[c[:, 1].astype(int), c[:, 0].astype(int)] = True
    h, w = occ.shape
    for x, y, r in circles:
        # only the window of cells the disc can touch (the same cells as testing the whole
        # grid, which costs grid size x circles)
        reach = r + 0.5 * res
        c0 = max(0, math.floor((x - reach - origin[0]) / res) - 1)
        c1 = min(w, math.ceil((x + reach - origin[0]) / res) + 2)
        r0 = max(0, math.floor((y - reach - origin[1]) / res) - 1)
        r1 = min(h, math.ceil((y + reach - origin[1]) / res) + 2)
        if c0 >= c1 or r0 >= r1:
            continue
        cx = (np.arange(c0, c1) + 0.5) * res + origin[0]
        cy = (np.arange(r0, r1) + 0.5) * res + origin[1]
        occ[r0:r1, c0:c1] |= (cx[None, :] - x) ** 2 + (cy[:, None] - y) ** 2 <= reach**2
    # clearance from the cell centre to the nearest occupied cell's boundary (conservative)
    dist = ndimage.distance_transform_edt(~occ).astype(np.float32) * res - 0.5 * res
    dist = np.maximum(dist, 0.0).astype(np.float32)
    labels, _ = ndimage.label(~occ)
    sc = np.floor((start[:2] - origin) / res).astype(int)
    lab = labels[sc[1], sc[0]] if 0 <= sc[1] < occ.shape[0] and 0 <= sc[0] < occ.shape[1] else 0
    if lab == 0:
        raise ConfigError(f"world {name!r}: robot start {start[:2].tolist()} is not in free space")
    region = labels == lab
    if region[0, :].any() or region[-1, :].any() or region[:, 0].any() or region[:, -1].any():
        raise ConfigError(
            f"world {name!r}: the free space around the start is not enclosed by walls"
        )
    return NavGrid(origin=origin, resolution=res, clearance=dist, region=region)
