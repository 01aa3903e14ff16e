"""Numba kernels: exact nearest neighbours on the target scan, and normals.

Two structures are built once per match and reused by every iteration:

- the *cover*: a fine grid whose every cell lists each target point within ``rho`` of the
  cell (points are duplicated into the few cells their ``rho``-square overlaps). A query
  scans the one list of its cell; when the best distance found is at most ``rho`` it is the
  true nearest neighbour, since any closer point lies within ``rho`` of the query and hence in
  that list. Near convergence this answers almost every query with one contiguous scan of
  ~10 points and no branching on cell ranges.
- the *grid*: a coarser uniform grid (counting sort of the target points by cell) for the
  rest (queries farther than ``rho`` from every point: early iterations, outliers). A query
  visits rings of cells around its own cell and stops as soon as the distance from the query
  to the unvisited part of the grid exceeds the best distance found.

Either way the neighbour is the true nearest one at any distance (the same answer as
``cKDTree``, up to ties), or the true nearest within ``max_dist`` when a correspondence
limit is set.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

# Cells per match are capped so that a few far outliers (a 80 m SICK beam) never make the
# grid huge; beyond the cap cells just grow, which costs speed, never exactness.
MAX_CELLS = 1 << 16
# Fewest rings of cells searched around a query before a brute-force scan takes over.
MAX_RINGS = 3
# The cover's cells are capped too; its radius never drops below COVER_MIN_RADIUS (m) nor
# below COVER_SPACING_FACTOR x the typical spacing of consecutive target points, so that
# sparse scans (1-degree SICK beams) still get most queries certified near convergence.
MAX_COVER_CELLS = 1 << 16
COVER_MIN_RADIUS = 0.05
COVER_SPACING_FACTOR = 2.0
# cover cell edge / cover radius
COVER_CELL_FACTOR = 2.0
# A target with more points than this many per query point and start gets no cover (`no_cover`):
# its build (~25 ns a point) then costs more than it saves. Measured on FR079's refinements
# against the local map, targets cut to r source sizes, ms per match with / without a cover:
# r = 2: 0.30 / 0.44, 8: 0.60 / 0.68, 16: 0.93 / 0.90, 32: 1.47 / 1.25, the whole local map
# (~43): 2.13 / 1.54. A scan-to-scan match (r ~ 1) keeps it (0.33 / 0.42).
COVER_MAX_TARGET_RATIO = 16
# Planarity of a block whose normal is not computed yet (`pending_block_normals`); a real one
# is >= 0 (-1: too few points, NaN: an empty cell's entry, never read).
BLOCK_PENDING = -2.0

# (start, sorted points, x0, y0, cell, nx, ny) of `build_grid`
Grid = tuple[NDArray[np.int64], NDArray[np.float64], float, float, float, int, int]
# (start, x and y of the listed points, their indices into the grid's sorted points, x0, y0,
# 1 / cell, nx, ny, rho^2) of `build_cover`
Cover = tuple[
    NDArray[np.int32], NDArray[np.float64], NDArray[np.float64], NDArray[np.int32], float,
    float, float, int, int, float,
]  # fmt: skip


# Every kernel is ``nogil=True``: it touches no Python object, and releasing the GIL lets the
# back-end instances of a run update side by side on threads (`scanguard.slam.loop.RunLoop`).
@njit(cache=True, error_model="numpy", nogil=True)
def kth_smallest(a: NDArray[np.float64], k: int) -> float:
    """The ``k``-th smallest value of ``a`` (0-based), reordering ``a`` in place around it.

    Hoare's quickselect. ``np.partition`` and ``np.median`` give the same value (an order
    statistic is one value, however it is found), but numba's generic versions of them
    took ~5 s each to compile in every cold process, most of the first match's wait.
    On return every value before ``k`` is at most ``a[k]`` and every value after it at
    least ``a[k]`` (`median` reads the next one from that). NaN-free input.
    """
    lo = 0
    hi = a.shape[0] - 1
    while lo < hi:
        pivot = a[(lo + hi) >> 1]
        i = lo
        j = hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                t = a[i]
                a[i] = a[j]
                a[j] = t
                i += 1
                j -= 1
        # [lo, j] <= pivot, [i, hi] >= pivot, and what lies between equals it
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


@njit(cache=True, error_model="numpy", nogil=True)
def median(a: NDArray[np.float64]) -> float:
    """``np.median`` of a NaN-free 1-D array, bit for bit, without reordering ``a``.

    The mean of the two middle values of an even count is numba's own ``(lo + hi) / 2``.
    """
    n = a.shape[0]
    if n == 0:
        return np.nan
    b = a.copy()
    half = n >> 1
    if n & 1:
        return kth_smallest(b, half)
    lo = kth_smallest(b, half - 1)
    hi = b[half]
    for i in range(half + 1, n):
        hi = min(hi, b[i])
    return (lo + hi) / 2


@njit(cache=True, error_model="numpy", nogil=True)
def choose_cell_size(pts: NDArray[np.float64], cell_size: float) -> float:
    """Cell edge (m): ``cell_size`` unless the bounding box would need more than MAX_CELLS."""
    n = pts.shape[0]
    if n == 0:
        return cell_size
    x0 = pts[0, 0]
    y0 = pts[0, 1]
    x1 = x0
    y1 = y0
    for i in range(n):
        x0 = min(x0, pts[i, 0])
        x1 = max(x1, pts[i, 0])
        y0 = min(y0, pts[i, 1])
        y1 = max(y1, pts[i, 1])
    area = (x1 - x0 + cell_size) * (y1 - y0 + cell_size)
    return max(cell_size, math.sqrt(area / MAX_CELLS))


@njit(cache=True, error_model="numpy", nogil=True)
def build_grid(
    pts: NDArray[np.float64], cell: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], float, float, int, int]:
    """Sort ``pts`` by grid cell.

    Returns:
        ``(start, order, sorted_pts, x0, y0, nx, ny)``: points of cell ``c = iy * nx + ix`` are
        ``sorted_pts[start[c]:start[c + 1]]`` and ``order`` maps them back to input indices.
    """
    n = pts.shape[0]
    x0 = pts[0, 0]
    y0 = pts[0, 1]
    x1 = x0
    y1 = y0
    for i in range(n):
        x0 = min(x0, pts[i, 0])
        x1 = max(x1, pts[i, 0])
        y0 = min(y0, pts[i, 1])
        y1 = max(y1, pts[i, 1])
    nx = int((x1 - x0) / cell) + 1
    ny = int((y1 - y0) / cell) + 1
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    cid = np.empty(n, dtype=np.int64)
    inv = 1.0 / cell
    for i in range(n):
        cx = min(int((pts[i, 0] - x0) * inv), nx - 1)
        cy = min(int((pts[i, 1] - y0) * inv), ny - 1)
        c = cy * nx + cx
        cid[i] = c
        start[c + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    cursor = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    sorted_pts = np.empty((n, 2), dtype=np.float64)
    for i in range(n):
        c = cid[i]
        j = cursor[c]
        cursor[c] += 1
        order[j] = i
        sorted_pts[j, 0] = pts[i, 0]
        sorted_pts[j, 1] = pts[i, 1]
    return start, order, sorted_pts, x0, y0, nx, ny


@njit(cache=True, error_model="numpy", nogil=True)
def _scan_cell(
    c: int,
    qx: float,
    qy: float,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    best: float,
    bi: int,
) -> tuple[float, int]:
    for j in range(start[c], start[c + 1]):
        dx = spts[j, 0] - qx
        dy = spts[j, 1] - qy
        d2 = dx * dx + dy * dy
        if d2 < best or (bi < 0 and d2 <= best):
            best = d2
            bi = j
    return best, bi


@njit(cache=True, error_model="numpy", nogil=True)
def nearest(
    qx: float,
    qy: float,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    max_d2: float,
    seed: int = -1,
) -> tuple[int, float]:
    """Index into ``spts`` of the nearest point to ``(qx, qy)`` and its squared distance.

    ``seed`` (an index, -1: none) is a candidate whose distance prunes the search. Returns
    ``(-1, inf)`` when no point lies within ``sqrt(max_d2)`` (``max_d2 = inf``: none).
    """
    fx = (qx - x0) / cell
    fy = (qy - y0) / cell
    cx = 0 if fx < 0 else (nx - 1 if fx >= nx else int(fx))
    cy = 0 if fy < 0 else (ny - 1 if fy >= ny else int(fy))
    best = max_d2
    bi = -1
    if seed >= 0:
        dx = spts[seed, 0] - qx
        dy = spts[seed, 1] - qy
        d2 = dx * dx + dy * dy
        if d2 <= best:
            best = d2
            bi = seed
    # Fast path (almost every query once ICP is near convergence): the 3x3 block around the
    # query's cell holds every point closer than one cell edge.
    for iy in range(max(cy - 1, 0), min(cy + 1, ny - 1) + 1):
        row = iy * nx
        for ix in range(max(cx - 1, 0), min(cx + 1, nx - 1) + 1):
            best, bi = _scan_cell(row + ix, qx, qy, start, spts, best, bi)
    # Whether or not the query is inside the grid, every point within one cell edge of it
    # lies in that block.
    if best <= cell * cell:
        return (bi, best) if bi >= 0 else (-1, np.inf)
    # rings cost ~8k cells each: past this many, one brute-force pass is cheaper
    max_rings = max(MAX_RINGS, int(math.sqrt(spts.shape[0]) / 4))
    k = 2
    while True:
        if k > max_rings:
            # Far from every target point (an outlier, or a bad initial guess): a brute-force
            # scan is cheaper than many more rings, and just as exact.
            for j in range(spts.shape[0]):
                dx = spts[j, 0] - qx
                dy = spts[j, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 < best or (bi < 0 and d2 <= best):
                    best = d2
                    bi = j
            break
        xlo = cx - k
        xhi = cx + k
        ylo = cy - k
        yhi = cy + k
        if xlo < 0 and ylo < 0 and xhi >= nx and yhi >= ny:
            break
        for iy in range(max(ylo, 0), min(yhi, ny - 1) + 1):
            edge_row = iy in (ylo, yhi)
            for ix in range(max(xlo, 0), min(xhi, nx - 1) + 1):
                if not edge_row and ix != xlo and ix != xhi:
                    continue
                c = iy * nx + ix
                if start[c] == start[c + 1]:
                    continue
                # skip cells that cannot hold a closer point than the best so far
                bx = x0 + ix * cell
                ex = bx - qx if qx < bx else (qx - bx - cell if qx > bx + cell else 0.0)
                by = y0 + iy * cell
                ey = by - qy if qy < by else (qy - by - cell if qy > by + cell else 0.0)
                if ex * ex + ey * ey > best:
                    continue
                best, bi = _scan_cell(c, qx, qy, start, spts, best, bi)
        # Distance from the query to the unvisited cells: they lie beyond one of the
        # ring's sides that is not at the grid border.
        lb = np.inf
        if xlo > 0:
            lb = min(lb, qx - (x0 + xlo * cell))
        if xhi < nx - 1:
            lb = min(lb, x0 + (xhi + 1) * cell - qx)
        if ylo > 0:
            lb = min(lb, qy - (y0 + ylo * cell))
        if yhi < ny - 1:
            lb = min(lb, y0 + (yhi + 1) * cell - qy)
        if lb == np.inf:
            break
        if lb > 0.0 and lb * lb >= best:
            break
        k += 1
    if bi < 0:
        return -1, np.inf
    return bi, best


@njit(cache=True, error_model="numpy", nogil=True)
def nearest_fast(
    qx: float,
    qy: float,
    h1: int,
    h2: int,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    inv: float,
    nx: int,
    ny: int,
    max_d2: float,
) -> tuple[int, float]:
    """Fast path of `nearest` from candidate neighbours ``h1``/``h2`` (indices, -1: none).

    ICP queries are coherent: a point's neighbour at the last iteration, or the neighbour of
    the previous point of the scan, is usually (nearly) the answer. Its distance bounds the
    search to the few cells that overlap that disc, so the result stays the exact nearest.
    Returns ``(-2, candidate)`` when the candidates do not help enough (none within
    ``max_d2``, or a disc over too many cells): the caller then runs `nearest` seeded with
    the candidate (-1: none). The second value is the squared distance otherwise. Kept
    apart from `nearest` so that this small function inlines into the ICP loops.
    """
    best = max_d2
    bi = -1
    if h1 >= 0:
        dx = spts[h1, 0] - qx
        dy = spts[h1, 1] - qy
        d2 = dx * dx + dy * dy
        if d2 <= best:
            best = d2
            bi = h1
    if h2 >= 0 and h2 != h1:
        dx = spts[h2, 0] - qx
        dy = spts[h2, 1] - qy
        d2 = dx * dx + dy * dy
        if d2 < best or (bi < 0 and d2 <= best):
            best = d2
            bi = h2
    if bi < 0:
        return -2, -1
    # Counting sort is stable, so within a cell the sorted points keep the input (beam)
    # order: stepping to the adjacent sorted point that is closer walks along the surface
    # and shrinks the search disc, at the cost of a contiguous read or two.
    n = spts.shape[0]
    for _step in range(8):
        moved = False
        for nb in (bi - 1, bi + 1):
            if 0 <= nb < n:
                dx = spts[nb, 0] - qx
                dy = spts[nb, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 < best:
                    best = d2
                    bi = nb
                    moved = True
        if not moved:
            break
    # Cells overlapping the disc of radius sqrt(best) around the query (clamped: every point
    # is inside the grid). Same arithmetic as `build_grid` (subtract, then multiply by
    # 1/cell; both monotonic), widened by a hair, so no point of the disc is missed.
    r = math.sqrt(best) * (1.0 + 1e-9) + 1e-12
    a = (qx - r - x0) * inv
    ix0 = int(a) if a > 0.0 else 0
    a = (qy - r - y0) * inv
    iy0 = int(a) if a > 0.0 else 0
    a = (qx + r - x0) * inv
    ix1 = min(int(a), nx - 1) if a > 0.0 else -1
    a = (qy + r - y0) * inv
    iy1 = min(int(a), ny - 1) if a > 0.0 else -1
    if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) > 25:
        return -2, bi
    for iy in range(iy0, iy1 + 1):
        row = iy * nx
        for ix in range(ix0, ix1 + 1):
            c = row + ix
            for j in range(start[c], start[c + 1]):
                dx = spts[j, 0] - qx
                dy = spts[j, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 < best:
                    best = d2
                    bi = j
    return bi, best


@njit(cache=True, error_model="numpy", nogil=True)
def _pca_normal(
    cnt: float, sx: float, sy: float, sxx: float, sxy: float, syy: float
) -> tuple[float, float, float]:
    # moments are relative to the point itself, so no catastrophic cancellation far away
    mx = sx / cnt
    my = sy / cnt
    a = sxx / cnt - mx * mx
    b = sxy / cnt - mx * my
    d = syy / cnt - my * my
    disc = math.sqrt(max((a - d) * (a - d) * 0.25 + b * b, 0.0))
    lmax = 0.5 * (a + d) + disc
    lmin = 0.5 * (a + d) - disc
    if lmax <= 0.0:
        return 0.0, 0.0, 0.0
    # Eigenvector of lmin: both (lmin - d, b) and (b, lmin - a) are; take the longer one, as
    # the other is all rounding noise when b ~ 0 (e.g. a wall symmetric about the point).
    if abs(lmin - a) >= abs(lmin - d):
        vx = b
        vy = lmin - a
    else:
        vx = lmin - d
        vy = b
    nrm = math.hypot(vx, vy)
    if nrm <= 0.0:
        return 0.0, 0.0, 0.0
    return vx / nrm, vy / nrm, 1.0 - max(lmin, 0.0) / lmax


@njit(cache=True, error_model="numpy", nogil=True)
def block_normals(
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    min_neighbors: int,
) -> NDArray[np.float64]:
    """Normals of every 2x2 block of grid cells that holds points, by PCA.

    A point's block is the 2x2 block of cells nearest to it (see `point_normal`). Returns
    ``bcache`` ``(n, 4, 3)``: per (cell, quadrant of the point in its cell), keyed by the
    cell's first sorted index, ``(nx, ny, planarity)``, or planarity -1 when the block holds
    fewer than ``min_neighbors`` points (other rows are never read). Each block is computed
    once (`fill_block`) and written to the (cell, quadrant) entries of its up to four cells:
    ~30 us per scan, where a lazy per-point computation cost ~4x that. A large target fills
    them as they are read instead (`pending_block_normals`), to the same numbers.
    """
    bcache = pending_block_normals(start, spts.shape[0], nx * ny)
    for cy in range(ny):
        for cx in range(nx):
            k = start[cy * nx + cx]
            if k == start[cy * nx + cx + 1]:
                continue
            for quad in range(4):
                if bcache[k, quad, 2] == BLOCK_PENDING:  # else done from another of its cells
                    fill_block(cx, cy, quad, start, spts, x0, y0, cell, nx, ny, min_neighbors,
                               bcache)  # fmt: skip
    return bcache


@njit(cache=True, error_model="numpy", nogil=True)
def pending_block_normals(start: NDArray[np.int64], m: int, ncell: int) -> NDArray[np.float64]:
    """A `block_normals` cache with every block pending, to be filled as its points are read.

    `cached_normal` computes a block the first time one of its points is read (`fill_block`),
    to the same numbers. For a target much larger than the source (a local map against one
    scan), whose pairs read a few hundred of its thousands of blocks: ~0.25 ms of a ~1.6 ms
    match saved.
    """
    bcache = np.empty((m, 4, 3))
    for c in range(ncell):
        k = start[c]
        if k < start[c + 1]:
            for q in range(4):
                bcache[k, q, 2] = BLOCK_PENDING
    return bcache


@njit(cache=True, error_model="numpy", nogil=True)
def fill_block(
    cx: int,
    cy: int,
    quad: int,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    min_neighbors: int,
    bcache: NDArray[np.float64],
) -> None:
    """The block of quadrant ``quad`` of cell ``(cx, cy)`` into ``bcache``, as `block_normals`.

    Each cell's moments (count, first and second moments about its corner: small numbers
    wherever the scan lies) are summed over its points in their order and shifted to the
    block's corner; written to the (cell, quadrant) entries of the block's cells.
    """
    bx = cx if quad & 1 else cx - 1
    by = cy if quad & 2 else cy - 1
    cnt = 0.0
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    sxy = 0.0
    syy = 0.0
    for iy in range(max(by, 0), min(by + 1, ny - 1) + 1):
        oy = (iy - by) * cell
        for ix in range(max(bx, 0), min(bx + 1, nx - 1) + 1):
            c = iy * nx + ix
            if start[c] == start[c + 1]:
                continue
            ox = (ix - bx) * cell
            # the cell's moments about its corner
            w = 0.0
            mx = 0.0
            my = 0.0
            mxx = 0.0
            mxy = 0.0
            myy = 0.0
            for k in range(start[c], start[c + 1]):
                dx = spts[k, 0] - (x0 + ix * cell)
                dy = spts[k, 1] - (y0 + iy * cell)
                w += 1.0
                mx += dx
                my += dy
                mxx += dx * dx
                mxy += dx * dy
                myy += dy * dy
            cnt += w
            sx += mx + w * ox
            sy += my + w * oy
            sxx += mxx + 2.0 * ox * mx + w * ox * ox
            sxy += mxy + ox * my + oy * mx + w * ox * oy
            syy += myy + 2.0 * oy * my + w * oy * oy
    a = 0.0
    b = 0.0
    p = -1.0  # too few points in the block: `point_normal` uses a disc
    if cnt >= min_neighbors:
        a, b, p = _pca_normal(cnt, sx, sy, sxx, sxy, syy)
    for iy in range(max(by, 0), min(by + 1, ny - 1) + 1):
        for ix in range(max(bx, 0), min(bx + 1, nx - 1) + 1):
            c = iy * nx + ix
            k = start[c]
            if k == start[c + 1]:
                continue
            q = (1 if ix == bx else 0) + (2 if iy == by else 0)
            bcache[k, q, 0] = a
            bcache[k, q, 1] = b
            bcache[k, q, 2] = p


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def cached_normal(
    i: int,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    radius: float,
    min_neighbors: int,
    bcache: NDArray[np.float64],
) -> tuple[float, float, float]:
    """`point_normal`'s ``(nx, ny, planarity)`` for sorted point ``i`` from `block_normals`.

    NaNs when the point needs the disc instead (``cell > radius``, or a sparse block): the
    caller then calls `point_normal`. A pending block (`pending_block_normals`) is computed
    first. Inlined: ~10 ns, where the call costs ~100 ns.
    """
    if cell > radius:
        return np.nan, np.nan, np.nan
    # same arithmetic as `build_grid`, so that (cx, cy) is the cell holding point i
    inv = 1.0 / cell
    fx = (spts[i, 0] - x0) * inv
    fy = (spts[i, 1] - y0) * inv
    cx = min(int(fx), nx - 1)
    cy = min(int(fy), ny - 1)
    key = start[cy * nx + cx]
    quad = (1 if fx - cx >= 0.5 else 0) + (2 if fy - cy >= 0.5 else 0)
    if bcache[key, quad, 2] == BLOCK_PENDING:
        fill_block(cx, cy, quad, start, spts, x0, y0, cell, nx, ny, min_neighbors, bcache)
    if bcache[key, quad, 2] >= 0.0:
        return bcache[key, quad, 0], bcache[key, quad, 1], bcache[key, quad, 2]
    return np.nan, np.nan, np.nan


@njit(cache=True, error_model="numpy", nogil=True)
def point_normal(
    i: int,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    radius: float,
    min_neighbors: int,
    bcache: NDArray[np.float64],
) -> tuple[float, float, float]:
    """Unit normal of sorted target point ``i`` by PCA of its neighbourhood.

    The neighbourhood is the 2x2 block of grid cells nearest to the point (a square of side
    ``2 * cell`` with the point at least ``cell / 2`` from its border) when
    ``cell <= radius``: cheap, as no distances are needed. Otherwise, or when that block
    holds fewer than ``min_neighbors`` points, it is the disc of ``radius``, doubled (up to
    three times) until it holds enough points, so sparse far points still get a normal.

    Block normals come from ``bcache``, the output of `block_normals` (all blocks of the
    scan, computed once per match).

    Returns:
        ``(nx, ny, planarity)``; ``(0, 0, 0)`` when no line fits (isolated point). Planarity
        is ``1 - lambda_min / lambda_max`` of the neighbourhood covariance.
    """
    px = spts[i, 0]
    py = spts[i, 1]
    a, b, p = cached_normal(i, start, spts, x0, y0, cell, nx, ny, radius, min_neighbors, bcache)
    if not math.isnan(a):
        return a, b, p
    r = radius
    for _attempt in range(4):
        r2 = r * r
        # only the cells that overlap the disc
        ix0 = max(int((px - r - x0) / cell), 0) if px - r > x0 else 0
        ix1 = min(int((px + r - x0) / cell), nx - 1)
        iy0 = max(int((py - r - y0) / cell), 0) if py - r > y0 else 0
        iy1 = min(int((py + r - y0) / cell), ny - 1)
        cnt = 0
        sx = 0.0
        sy = 0.0
        sxx = 0.0
        sxy = 0.0
        syy = 0.0
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                c = iy * nx + ix
                for j in range(start[c], start[c + 1]):
                    dx = spts[j, 0] - px
                    dy = spts[j, 1] - py
                    if dx * dx + dy * dy <= r2:
                        cnt += 1
                        sx += dx
                        sy += dy
                        sxx += dx * dx
                        sxy += dx * dy
                        syy += dy * dy
        if cnt >= min_neighbors:
            return _pca_normal(cnt, sx, sy, sxx, sxy, syy)
        r *= 2.0
    return 0.0, 0.0, 0.0


@njit(cache=True, error_model="numpy", nogil=True)
def grid_normals(
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    radius: float,
    min_neighbors: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """`point_normal` of every sorted target point: ``(normals (n, 2), planarity (n,))``."""
    n = spts.shape[0]
    normals = np.zeros((n, 2), dtype=np.float64)
    planarity = np.zeros(n, dtype=np.float64)
    bcache = block_normals(start, spts, x0, y0, cell, nx, ny, min_neighbors)
    for i in range(n):
        a, b, p = point_normal(i, start, spts, x0, y0, cell, nx, ny, radius, min_neighbors, bcache)
        normals[i, 0] = a
        normals[i, 1] = b
        planarity[i] = p
    return normals, planarity


@njit(cache=True, error_model="numpy", nogil=True)
def cover_radius(pts: NDArray[np.float64]) -> float:
    """Cover radius (m) for a scan, from its points in scan order.

    ``COVER_SPACING_FACTOR`` x the median spacing of consecutive points (a 64-sample
    estimate), at least ``COVER_MIN_RADIUS``.
    """
    n = pts.shape[0]
    if n < 2:
        return COVER_MIN_RADIUS
    k = min(64, n - 1)
    stride = (n - 1) // k
    gaps = np.empty(k)
    for m in range(k):
        i = m * stride
        gaps[m] = math.hypot(pts[i + 1, 0] - pts[i, 0], pts[i + 1, 1] - pts[i, 1])
    return max(COVER_MIN_RADIUS, COVER_SPACING_FACTOR * median(gaps))


@njit(cache=True, error_model="numpy", nogil=True)
def build_cover(spts: NDArray[np.float64], rho: float) -> Cover:
    """The cover of ``spts`` (see the module docstring).

    Cell lists of every point within ``rho`` of the cell; cells of edge
    ``COVER_CELL_FACTOR * rho`` (larger when that would exceed ``MAX_COVER_CELLS``).

    Each point is listed in every cell its square of half-side ``r`` (``rho`` widened by a
    hair) overlaps. The cell arithmetic of `cover_nearest` (subtract, multiply by 1/cell,
    truncate) is the same and monotonic, so a query within ``rho`` of a point always falls in
    one of that point's cells.
    """
    n = spts.shape[0]
    r = rho * (1.0 + 1e-9) + 1e-12
    x0 = spts[0, 0]
    y0 = spts[0, 1]
    x1 = x0
    y1 = y0
    for i in range(n):
        x0 = min(x0, spts[i, 0])
        x1 = max(x1, spts[i, 0])
        y0 = min(y0, spts[i, 1])
        y1 = max(y1, spts[i, 1])
    x0 -= r
    y0 -= r
    x1 += r
    y1 += r
    cell = COVER_CELL_FACTOR * rho
    cell = max(cell, math.sqrt((x1 - x0 + cell) * (y1 - y0 + cell) / MAX_COVER_CELLS))
    inv = 1.0 / cell
    nx = int((x1 - x0) * inv) + 1
    ny = int((y1 - y0) * inv) + 1
    ncell = nx * ny
    start = np.zeros(ncell + 1, dtype=np.int32)
    for i in range(n):
        ix0 = int((spts[i, 0] - r - x0) * inv)
        ix1 = min(int((spts[i, 0] + r - x0) * inv), nx - 1)
        iy0 = int((spts[i, 1] - r - y0) * inv)
        iy1 = min(int((spts[i, 1] + r - y0) * inv), ny - 1)
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                start[iy * nx + ix] += 1
    # Inclusive prefix sums, then a filling pass that counts each cell back down: no copy
    # of the offsets is needed, and filling in reverse keeps each list in index order.
    for c in range(1, ncell):
        start[c] += start[c - 1]
    start[ncell] = start[ncell - 1]
    tot = start[ncell]
    # separate x and y arrays: the list scan runs ~1.6x faster than on an (n, 2) array
    cx = np.empty(tot, dtype=np.float64)
    cy = np.empty(tot, dtype=np.float64)
    cid = np.empty(tot, dtype=np.int32)
    for i in range(n - 1, -1, -1):
        ix0 = int((spts[i, 0] - r - x0) * inv)
        ix1 = min(int((spts[i, 0] + r - x0) * inv), nx - 1)
        iy0 = int((spts[i, 1] - r - y0) * inv)
        iy1 = min(int((spts[i, 1] + r - y0) * inv), ny - 1)
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                c = iy * nx + ix
                k = start[c] - 1
                start[c] = k
                cx[k] = spts[i, 0]
                cy[k] = spts[i, 1]
                cid[k] = i
    return start, cx, cy, cid, x0, y0, inv, nx, ny, rho * rho


@njit(cache=True, error_model="numpy", nogil=True)
def no_cover() -> Cover:
    """A cover of no cells: every query goes to the grid (`grid_nearest`), exactly as well.

    The neighbours are the same, up to exact ties between equidistant points.
    """
    return (
        np.zeros(1, dtype=np.int32), np.empty(0), np.empty(0), np.empty(0, dtype=np.int32),
        0.0, 0.0, 1.0, 0, 0, 0.0,
    )  # fmt: skip


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def cover_nearest(
    qx: float,
    qy: float,
    start: NDArray[np.int32],
    cx: NDArray[np.float64],
    cy: NDArray[np.float64],
    cid: NDArray[np.int32],
    x0: float,
    y0: float,
    inv: float,
    nx: int,
    ny: int,
    rho2: float,
) -> tuple[int, float]:
    """Nearest point to ``(qx, qy)`` when the cover certifies it: ``(index, squared distance)``.

    Otherwise ``(-2, candidate)``: the best point of the cell's list (its index as a float,
    -1: none), a good seed for the full search. Takes the cover's fields one by one: the
    same function taking the `Cover` tuple ran ~1.4x slower inside the ICP loops.
    """
    fx = (qx - x0) * inv
    fy = (qy - y0) * inv
    # Early returns on purpose: the same logic as nested ifs compiled to a loop 2x slower.
    # Written so that NaN fails too; int() truncates towards 0, so negatives go first.
    if not (fx >= 0.0 and fy >= 0.0):
        return -2, -1.0
    ix = int(fx)
    iy = int(fy)
    if ix >= nx or iy >= ny:
        return -2, -1.0
    c = iy * nx + ix
    best = np.inf
    bk = -1
    for k in range(start[c], start[c + 1]):
        dx = cx[k] - qx
        dy = cy[k] - qy
        d2 = dx * dx + dy * dy
        if d2 < best:
            best = d2
            bk = k
    if bk < 0:
        return -2, -1.0
    if best <= rho2:
        return cid[bk], best
    return -2, float(cid[bk])


@njit(cache=True, error_model="numpy", nogil=True)
def grid_nearest(
    qx: float,
    qy: float,
    seed: int,
    h1: int,
    h2: int,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    max_d2: float,
) -> tuple[int, float]:
    """Exact nearest point by the grid alone: `nearest_fast` from hints, then `nearest`.

    The fallback after `cover_nearest` returns ``(-2, seed)``: ``seed`` (its candidate, -1:
    none) replaces hint ``h1`` (the point's last neighbour) when there is one; ``h2`` is the
    previous point's neighbour. Returns ``(index into the sorted points, d^2)``, ``(-1, inf)``
    when no point lies within ``sqrt(max_d2)``.

    `_core.nn_chunk` calls it for the queries its cover scan does not certify; it is a plain
    call, not inlined: an ``inline="always"`` helper nesting another made the loop 2x slower
    (numba inlines nested helpers into code LLVM optimises poorly).
    """
    if seed >= 0:
        h1 = seed
    j, d2 = nearest_fast(qx, qy, h1, h2, start, spts, x0, y0, 1.0 / cell, nx, ny, max_d2)
    if j == -2:
        j, d2 = nearest(qx, qy, start, spts, x0, y0, cell, nx, ny, max_d2, int(d2))
    return j, d2


@njit(cache=True, error_model="numpy", nogil=True)
def find_nearest(
    qx: float,
    qy: float,
    h1: int,
    h2: int,
    start: NDArray[np.int64],
    spts: NDArray[np.float64],
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cstart: NDArray[np.int32],
    cx: NDArray[np.float64],
    cy: NDArray[np.float64],
    cid: NDArray[np.int32],
    cx0: float,
    cy0: float,
    cinv: float,
    cnx: int,
    cny: int,
    rho2: float,
    max_d2: float,
) -> tuple[int, float]:
    """One query exactly as the ICP loops run it: `cover_nearest`, then `grid_nearest`.

    Arguments: the query, two hints (-1: none), the fields of a `Grid` and of a `Cover`
    (``find_nearest(qx, qy, h1, h2, *grid, *cover, max_d2)`` from Python) and the squared
    correspondence limit. Returns ``(index into the sorted points, d^2)``, ``(-1, inf)`` when
    no point lies within ``sqrt(max_d2)``. For tests and one-off queries; the loops inline
    the same lines.
    """
    j, d2 = cover_nearest(qx, qy, cstart, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2)
    if j == -2:
        j, d2 = grid_nearest(qx, qy, int(d2), h1, h2, start, spts, x0, y0, cell, nx, ny, max_d2)
    elif d2 > max_d2:
        j = -1
        d2 = np.inf
    return j, d2
