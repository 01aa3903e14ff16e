"""Numba kernels of the correlative scan matcher: likelihood table, pyramid, search.

Index conventions: the level-0 table has ``(ny, nx)`` cells, cell ``(j, i)`` covers
``[x0 + i r, x0 + (i + 1) r) x [y0 + j r, y0 + (j + 1) r)``. The pyramid ``stack`` has shape
``(levels, ny + pad, nx + pad)`` with ``pad = 2**(levels - 1) - 1``, and
``stack[h, j + pad, i + pad] = max(table[j:j + 2**h, i:i + 2**h])`` (cells outside the table
are 0). A candidate at height ``h`` with offset ``(dx, dy)`` stands for the ``2**h x 2**h``
finest offsets ``dx .. dx + 2**h - 1`` (and the same in y), so its score on level ``h`` is an
upper bound of all of theirs: branch-and-bound prunes exactly.

Scores are *sums* of table values over the source points (the caller divides by the count);
sums of termwise larger float32 values in the same order are never smaller (rounding is
monotone), so the bounds stay exact in floating point too.

The sums are in fact exact, whatever their order: a table value is 0 or at least
``exp(-4.5)`` (the smearing stops at 3 sigma), so every value is a float32 of exponent >= -7,
a whole multiple of ``2**-30``, and a float64 sum of fewer than ``2**23`` of them (times whole
weights) never rounds. `branch_and_bound` relies on it: it scores the runs of consecutive
points that fall in the same cell once, weighted by their length (`discretise_runs`), and gets
the sums of every point one by one, bit for bit. So do its sum kernels, compiled with
``fastmath={"reassoc", "contract"}``: the vectoriser may then add in any order and fuse each
multiply into its add (both exact here), which scores ~2.5x faster with AVX-512 gathers and
gives the same bits as the plain loop (tested against `brute_force`, which has no such flag).
Nothing else here may use those flags: the cell of a transformed point depends on the
rounding of every product.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: The fastmath flags of the sum kernels, and of no other (module docstring).
EXACT_SUMS = {"reassoc", "contract"}


# Every kernel is ``nogil=True``: it touches no Python object, and releasing the GIL lets the
# back-end instances of a run update side by side on threads (`scanguard.slam.loop.RunLoop`).
@njit(cache=True, error_model="numpy", nogil=True)
def bounds(points: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """``(xmin, ymin, xmax, ymax)`` of ``(N, 2)`` points (N >= 1), in one pass.

    numpy's ``min(axis=0)`` on an ``(N, 2)`` array reduces along the long, strided axis with
    an inner loop of length 2: min and max took ~0.8 ms together on an 11,000-point local
    map, this loop ~0.02 ms (loaded machine). Min and max are exact, so the grid built from
    them is the same.
    """
    xmin = points[0, 0]
    xmax = xmin
    ymin = points[0, 1]
    ymax = ymin
    for p in range(1, points.shape[0]):
        x = points[p, 0]
        y = points[p, 1]
        xmin = min(xmin, x)
        xmax = max(xmax, x)
        ymin = min(ymin, y)
        ymax = max(ymax, y)
    return xmin, ymin, xmax, ymax


@njit(cache=True, error_model="numpy", nogil=True)
def nearest_d2(
    points: NDArray[np.float64],
    x0: float,
    y0: float,
    res: float,
    nx: int,
    ny: int,
    cutoff: float,
) -> NDArray[np.float64]:
    """Per cell ``(ny, nx + pad)``: the least squared distance to a point (inf: none near).

    Distances are from the cell's centre; every distance within ``cutoff`` is the least one,
    a larger one may be too large (the cells of columns ``>= nx`` are padding). One pass
    over the points, each updating the cells of its ``cutoff`` window, replaces a distance
    transform.
    """
    # a point's window is whole blocks of 8 columns, so that the update of a row is one
    # vector operation (AVX-512: 8 doubles); the columns beyond the window are more than a
    # cutoff away (their centres, by half a cell at least), so the distances they get never
    # reach the table
    span = math.floor(2.0 * cutoff / res) + 2
    width = 8 * ((span + 7) // 8)
    d2min = np.full((ny, nx + width), np.inf)
    # a point's squared x distances, once per column rather than once per cell (the same
    # products, so the same sums)
    dx2 = np.empty(width)
    for p in range(points.shape[0]):
        px = points[p, 0]
        py = points[p, 1]
        i0 = max(0, math.floor((px - cutoff - x0) / res))
        i1 = min(nx - 1, math.floor((px + cutoff - x0) / res))
        j0 = max(0, math.floor((py - cutoff - y0) / res))
        j1 = min(ny - 1, math.floor((py + cutoff - y0) / res))
        if i1 < i0:
            continue  # beside the grid
        for q in range(width):
            ddx = x0 + ((i0 + q) + 0.5) * res - px
            dx2[q] = ddx * ddx
        for j in range(j0, j1 + 1):
            ddy = y0 + (j + 0.5) * res - py
            ddy2 = ddy * ddy
            row = d2min[j]  # a view: the inner loop indexes one dimension
            for b in range(0, width, 8):
                for q in range(8):  # a constant count: one vector operation
                    row[i0 + b + q] = min(row[i0 + b + q], dx2[b + q] + ddy2)
    return d2min


@njit(cache=True, error_model="numpy", nogil=True)
def _smear(
    d2min: NDArray[np.float64], sigma: float, cutoff: float, out: NDArray[np.float32]
) -> None:
    """``out[j, i] = exp(-d2min[j, i] / 2 sigma^2)`` as float32, 0 beyond ``cutoff``."""
    c2 = cutoff * cutoff
    inv = 0.5 / (sigma * sigma)
    ny, nx = out.shape
    for j in range(ny):
        row = out[j]
        for i in range(nx):
            d2 = d2min[j, i]
            row[i] = np.float32(math.exp(-d2 * inv)) if d2 <= c2 else np.float32(0.0)


@njit(cache=True, error_model="numpy", nogil=True)
def likelihood_stack(
    points: NDArray[np.float64],
    x0: float,
    y0: float,
    res: float,
    nx: int,
    ny: int,
    sigma: float,
    cutoff: float,
    levels: int,
) -> NDArray[np.float32]:
    """The smeared likelihood table of the points and its padded pyramid (module docstring).

    Returns ``(levels, ny + pad, nx + pad)``. Level 0 holds per cell ``exp(-d^2 / 2 sigma^2)``,
    ``d`` the distance from the cell centre to the nearest point (`nearest_d2`), 0 beyond
    ``cutoff``. Because ``float32(exp(-d2 * inv))`` never increases with ``d2``, this is
    exactly the table of the max over points of the per-point kernel (bit for bit), with one
    ``exp`` per cell instead of one per point and cell (3.4x faster on a local map). The
    table goes straight into level 0 of the stack and only the padding is zeroed (every
    other level is overwritten whole): a local map's stack is mostly empty cells, and
    zeroing and copying them cost a third of the build.
    """
    pad = (1 << (levels - 1)) - 1
    out = np.empty((levels, ny + pad, nx + pad), dtype=np.float32)
    out[0, :pad, :] = 0.0
    out[0, pad:, :pad] = 0.0
    _smear(nearest_d2(points, x0, y0, res, nx, ny, cutoff), sigma, cutoff, out[0, pad:, pad:])
    _pool(out)
    return out


@njit(cache=True, error_model="numpy", nogil=True)
def _pool(out: NDArray[np.float32]) -> None:
    """Levels ``1..`` of ``out`` from its level 0, in place.

    Level ``h`` is the max of four level ``h - 1`` values ``2**(h-1)`` cells apart (a window of
    ``2**h`` is two adjacent windows of ``2**(h-1)``), done separably in y then x: O(cells)
    per level whatever its window.
    """
    levels, hh, ww = out.shape
    t = np.empty(ww, dtype=np.float32)
    for h in range(1, levels):
        s = 1 << (h - 1)
        prev = out[h - 1]
        cur = out[h]
        # one row at a time: the y max into a row buffer that stays in cache, then the x max
        # (whole tables in between made it memory-bound: 30 MB moved for a 5-level local map);
        # the bounds are decided per row, not per cell, so the loops vectorise
        for a in range(hh):
            r0 = prev[a]
            if a + s < hh:
                r1 = prev[a + s]
                for b in range(ww):
                    t[b] = max(r0[b], r1[b])
            else:
                for b in range(ww):
                    t[b] = r0[b]
            c = cur[a]
            for b in range(ww - s):
                c[b] = max(t[b], t[b + s])
            # element loops, not slice copies: see `outline`
            for b in range(max(ww - s, 0), ww):
                c[b] = t[b]


@njit(cache=True, error_model="numpy", nogil=True)
def outline(
    p: NDArray[np.float64], spacing: float, max_gap: float, gap_beams: float, increment: float
) -> NDArray[np.float64]:
    """``p`` followed by the points filled into the gaps it joins (`likelihood.outline_points`).

    Neighbours ``a, b`` are joined when ``spacing < d <= min(max_gap, gap_beams r increment)``,
    ``d`` their distance and ``r`` the nearer one's range (``increment`` >= 0); a gap gets
    ``k = ceil(d / spacing) - 1`` points at ``a + t (b - a)``, ``t = 1 .. k`` over ``k + 1``.
    The operations are numpy's vectorised ones of the function it replaced, in the same
    order, so the points are the same bit for bit (``tests/test_correlative.py``); one pass
    instead of ~20 small array operations (a third of a graph node's geometry).
    """
    n = p.shape[0]
    ks = np.zeros(max(n - 1, 0), dtype=np.int64)
    total = 0
    for i in range(n - 1):
        ax = p[i, 0]
        ay = p[i, 1]
        bx = p[i + 1, 0]
        by = p[i + 1, 1]
        d = math.hypot(bx - ax, by - ay)
        r = min(math.hypot(ax, ay), math.hypot(bx, by))
        if d > spacing and d <= min(max_gap, gap_beams * r * increment):
            # int(): numba's math.ceil of a float is a float
            k = int(math.ceil(d / spacing)) - 1  # noqa: RUF046
            ks[i] = k
            total += k
    out = np.empty((n + total, 2))
    # an element loop, not ``out[:n] = p``: numba compiled its first array-to-array slice
    # copy of a process in ~3 s, which every cold process paid for this one line
    for i in range(n):
        out[i, 0] = p[i, 0]
        out[i, 1] = p[i, 1]
    m = n
    for i in range(n - 1):
        k = ks[i]
        if k == 0:
            continue
        ax = p[i, 0]
        ay = p[i, 1]
        ex = p[i + 1, 0] - ax
        ey = p[i + 1, 1] - ay
        for q in range(k):
            t = (q + 1) / (k + 1)
            out[m, 0] = ax + t * ex
            out[m, 1] = ay + t * ey
            m += 1
    return out


#: `thin` marks squares in a bitmap of the points' lattice up to this many squares (16 MB);
#: beyond, in a hash table of the squares seen.
THIN_BITMAP_SQUARES = 1 << 27


@njit(cache=True, error_model="numpy", nogil=True)
def thin(points: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """Indices of the first point in each ``cell`` x ``cell`` square of a lattice, in order.

    Square ``(floor(x / cell), floor(y / cell))``: the lattice is the map frame's, not the
    points' bounding box's. A bitmap of the squares over the bounding box (a local map 37 x
    26 m at 1 cm is 1.2 MB: ~0.5 ms for 65,000 points, where a hash table took 2.5 ms with
    a cache miss per point); a hash table when the box is too large for one.
    """
    n = points.shape[0]
    xmin, ymin, xmax, ymax = bounds(points)
    ix0 = math.floor(xmin / cell)
    iy0 = math.floor(ymin / cell)
    nx = math.floor(xmax / cell) - ix0 + 1
    ny = math.floor(ymax / cell) - iy0 + 1
    if nx * ny > THIN_BITMAP_SQUARES:
        return _thin_hashed(points, cell)
    words = np.zeros((nx * ny + 63) // 64, dtype=np.uint64)
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for p in range(n):
        k = (math.floor(points[p, 1] / cell) - iy0) * nx + (math.floor(points[p, 0] / cell) - ix0)
        bit = np.uint64(1) << np.uint64(k & 63)
        if words[k >> 6] & bit == 0:
            words[k >> 6] |= bit
            keep[m] = p
            m += 1
    return keep[:m]


@njit(cache=True, error_model="numpy", nogil=True)
def _thin_hashed(points: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """`thin` by an open-addressing hash of the squares (a table of at least 2N, a power of 2)."""
    n = points.shape[0]
    bits = 1
    while (1 << bits) < 2 * n:
        bits += 1
    size = 1 << bits
    shift = np.uint64(64 - bits)
    used = np.zeros(size, dtype=np.bool_)
    kx = np.empty(size, dtype=np.int64)
    ky = np.empty(size, dtype=np.int64)
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for p in range(n):
        ix = np.int64(math.floor(points[p, 0] / cell))
        iy = np.int64(math.floor(points[p, 1] / cell))
        # Fibonacci hashing: the *top* bits of the products (their low bits depend only on
        # the low bits of the coordinates, and neighbouring squares would cluster); unsigned,
        # so the products wrap and the shift is logical
        u = np.uint64(ix) * np.uint64(0x9E3779B97F4A7C15) ^ np.uint64(iy) * np.uint64(
            0xC2B2AE3D27D4EB4F
        )
        h = np.int64(u >> shift)
        while used[h] and (kx[h] != ix or ky[h] != iy):
            h = (h + 1) & (size - 1)
        if not used[h]:
            used[h] = True
            kx[h] = ix
            ky[h] = iy
            keep[m] = p
            m += 1
    return keep[:m]


@njit(cache=True, error_model="numpy", nogil=True)
def discretise(
    src: NDArray[np.float64],
    px: float,
    py: float,
    pth: float,
    offsets: NDArray[np.float64],
    x0: float,
    y0: float,
    res: float,
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """Cell indices of the source points under each candidate rotation.

    Returns ``(ix, iy)``, each ``(len(offsets), n)``, under the poses
    ``(px, py, pth + offsets[k])``; a translation by whole cells then only adds to them.
    """
    k_n = offsets.shape[0]
    n = src.shape[0]
    ix = np.empty((k_n, n), dtype=np.int32)
    iy = np.empty((k_n, n), dtype=np.int32)
    inv = 1.0 / res
    # far-away points are clamped: any index this far out reads 0 for every offset of any
    # window the caller can ask for, and int32 cannot overflow
    lim = 1 << 29
    for k in range(k_n):
        c = math.cos(pth + offsets[k])
        s = math.sin(pth + offsets[k])
        for p in range(n):
            qx = c * src[p, 0] - s * src[p, 1] + px
            qy = s * src[p, 0] + c * src[p, 1] + py
            fx = math.floor((qx - x0) * inv)
            fy = math.floor((qy - y0) * inv)
            ix[k, p] = np.int32(min(max(fx, -lim), lim))
            iy[k, p] = np.int32(min(max(fy, -lim), lim))
    return ix, iy


@njit(cache=True, error_model="numpy", nogil=True)
def discretise_runs(
    src: NDArray[np.float64],
    px: float,
    py: float,
    pth: float,
    offsets: NDArray[np.float64],
    x0: float,
    y0: float,
    res: float,
) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.float64], NDArray[np.int64]]:
    """`discretise` with consecutive points in the same cell merged: ``(ix, iy, weight, count)``.

    Row ``k`` of the merged ``ix``, ``iy`` holds ``count[k]`` cells (the rest is unused), each
    weighted by the number of consecutive points it stands for. Neighbouring beams of a scan
    often hit one cell (40 % of FR079's points at 5 cm), and a cell is read once per
    candidate instead of once per point; the weighted sums are the same (module docstring).
    One pass, without `discretise`'s per-point arrays in between (the same cells: the same
    arithmetic).
    """
    k_n = offsets.shape[0]
    n = src.shape[0]
    mx = np.empty((k_n, n), dtype=np.int32)
    my = np.empty((k_n, n), dtype=np.int32)
    wt = np.empty((k_n, n), dtype=np.float64)
    cnt = np.zeros(k_n, dtype=np.int64)
    if n == 0:
        return mx, my, wt, cnt
    inv = 1.0 / res
    # `discretise`'s clamp, in floats: the same cells for every finite point (whole numbers
    # below 2^29 convert exactly), and a loop that vectorises (the int64 one did not)
    lim = float(1 << 29)
    sx = np.ascontiguousarray(src[:, 0])
    sy = np.ascontiguousarray(src[:, 1])
    fa = np.empty(n, dtype=np.int32)
    fb = np.empty(n, dtype=np.int32)
    for k in range(k_n):
        c = math.cos(pth + offsets[k])
        s = math.sin(pth + offsets[k])
        # the cells first, in a loop of their own that vectorises; then the runs
        for p in range(n):
            qx = c * sx[p] - s * sy[p] + px
            qy = s * sx[p] + c * sy[p] + py
            fa[p] = np.int32(min(max(np.floor((qx - x0) * inv), -lim), lim))
            fb[p] = np.int32(min(max(np.floor((qy - y0) * inv), -lim), lim))
        j = 0
        mx[k, 0] = fa[0]
        my[k, 0] = fb[0]
        wt[k, 0] = 1.0
        for p in range(1, n):
            a = fa[p]
            b = fb[p]
            if mx[k, j] == a and my[k, j] == b:
                wt[k, j] += 1.0
            else:
                j += 1
                mx[k, j] = a
                my[k, j] = b
                wt[k, j] = 1.0
        cnt[k] = j + 1
    return mx, my, wt, cnt


# fastmath: exact sums (module docstring), so any order of the adds gives the same bits
@njit(cache=True, error_model="numpy", nogil=True, fastmath=EXACT_SUMS)
def _sum_children(
    level: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    wt: NDArray[np.float64],
    count: int,
    k: int,
    dx: int,
    dy: int,
    half: int,
) -> tuple[float, float, float, float]:
    """Sums over merged runs (`discretise_runs`) at four offsets, in one pass over the runs.

    The offsets are ``(dx, dy)``, ``(dx + half, dy)``, ``(dx, dy + half)`` and
    ``(dx + half, dy + half)``, in that order: a candidate's four children, or a 2 x 2 block
    of a lattice (`_lattice_sums`). Each is ``sum(weight * level[iy + dy + pad, ix + dx + pad])``
    over the runs, cells off the table counting 0. A run's cell and weight are loaded once
    for the four; each sum still adds its runs one by one in order, so it is the sum a pass
    of its own would give (exact anyway, module docstring). A single offset is a block too
    (`_lattice_sums`); the brute force, the reference, reads every point once per pose
    (`_sum_at`, without weights or fastmath).
    """
    hh, ww = level.shape
    s00 = 0.0
    s10 = 0.0
    s01 = 0.0
    s11 = 0.0
    ox = dx + pad
    oy = dy + pad
    for p in range(count):
        a = iy[k, p] + oy
        b = ix[k, p] + ox
        a2 = a + half
        b2 = b + half
        w = wt[k, p]
        if 0 <= a < hh:
            if 0 <= b < ww:
                s00 += w * level[a, b]
            if 0 <= b2 < ww:
                s10 += w * level[a, b2]
        if 0 <= a2 < hh:
            if 0 <= b < ww:
                s01 += w * level[a2, b]
            if 0 <= b2 < ww:
                s11 += w * level[a2, b2]
    return s00, s10, s01, s11


@njit(cache=True, error_model="numpy", nogil=True)
def _lattice_sums(
    level: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    wt: NDArray[np.float64],
    count: int,
    k: int,
    dx0: int,
    dy0: int,
    m: int,
    step: int,
    out: NDArray[np.float64],
) -> None:
    """``out[a * m + b]``: the sum at ``(dx0 + a step, dy0 + b step)``, ``a, b < m``.

    2 x 2 blocks of the lattice in one pass each (`_sum_children`); an odd ``m``'s last row
    and column are blocks too, whose cells beyond the lattice are summed and dropped.
    """
    for a in range(0, m, 2):
        for b in range(0, m, 2):
            dx = dx0 + a * step
            dy = dy0 + b * step
            if a + 1 < m and b + 1 < m:
                four = _sum_children(level, pad, ix, iy, wt, count, k, dx, dy, step)
                out[a * m + b] = four[0]
                out[(a + 1) * m + b] = four[1]
                out[a * m + b + 1] = four[2]
                out[(a + 1) * m + b + 1] = four[3]
                continue
            # an odd m's last row or column: the block's other cells lie beyond it
            four = _sum_children(level, pad, ix, iy, wt, count, k, dx, dy, step)
            out[a * m + b] = four[0]
            if a + 1 < m:
                out[(a + 1) * m + b] = four[1]
            if b + 1 < m:
                out[a * m + b + 1] = four[2]


@njit(cache=True, error_model="numpy", nogil=True)
def _sum_at(
    level: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    k: int,
    dx: int,
    dy: int,
) -> float:
    hh, ww = level.shape
    total = 0.0
    ox = dx + pad
    oy = dy + pad
    for p in range(ix.shape[1]):
        a = iy[k, p] + oy
        b = ix[k, p] + ox
        if 0 <= a < hh and 0 <= b < ww:
            total += level[a, b]
    return total


@njit(cache=True, error_model="numpy", nogil=True)
def _block_excluded(dx: int, dy: int, h: int, ex_dx: int, ex_dy: int, ex_r2: float) -> bool:
    """Whether every offset of the ``2**h`` block at ``(dx, dy)`` lies in the disc."""
    size = (1 << h) - 1
    # the block's farthest corner from the disc's centre decides
    fx = max(abs(dx - ex_dx), abs(dx + size - ex_dx))
    fy = max(abs(dy - ex_dy), abs(dy + size - ex_dy))
    return float(fx * fx + fy * fy) <= ex_r2


@njit(cache=True, error_model="numpy", nogil=True)
def top_sums(
    stack: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    wt: NDArray[np.float64],
    count: NDArray[np.int64],
    w: int,
    levels: int,
    k_lo: int,
    k_hi: int,
    cs: NDArray[np.float64],
) -> None:
    """Scores of the coarsest candidates of angles ``k_lo..k_hi - 1``, into ``cs``.

    Candidate ``c = (k m + a) m + b`` (``m = 2 w // 2**(levels - 1) + 1``) is angle ``k`` at
    offset ``(-w + a step, -w + b step)``; each angle's slice is written by one call only, so
    two threads may fill halves of ``cs`` side by side (`branch_and_bound_lanes`).
    """
    top = levels - 1
    step = 1 << top
    m = (2 * w) // step + 1
    lvl = stack[top]
    sums = np.empty(m * m)
    for k in range(k_lo, k_hi):
        _lattice_sums(lvl, pad, ix, iy, wt, count[k], k, -w, -w, m, step, sums)
        base = k * m * m
        for c in range(m * m):  # not a slice copy: see `outline`
            cs[base + c] = sums[c]


@njit(cache=True, error_model="numpy", nogil=True)
def _others(shared: NDArray[np.float64], lane: int) -> float:
    """The best score so far of every lane but ``lane``."""
    out = -np.inf
    for j in range(shared.shape[0]):
        if j != lane and shared[j] > out:
            out = shared[j]
    return out


@njit(cache=True, error_model="numpy", nogil=True)
def sort_order(cs: NDArray[np.float64]) -> NDArray[np.int64]:
    """``np.argsort(cs)`` as `branch_and_bound` sorts (numba's sort, whose ties decide)."""
    return np.argsort(cs)


@njit(cache=True, error_model="numpy", nogil=True)
def descend(
    stack: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    wt: NDArray[np.float64],
    count: NDArray[np.int64],
    w: int,
    levels: int,
    threshold: float,
    ex_dx: int,
    ex_dy: int,
    ex_r2: float,
    cs: NDArray[np.float64],
    order: NDArray[np.int64],
    lane: int,
    shared: NDArray[np.float64],
) -> tuple[int, int, int, float, int, bool, int]:
    """Depth-first search below the coarsest candidates ``order[t]``, ``t = lane mod lanes``.

    The roots are taken best first (``t`` from the end of ``order``, ascending scores), each
    subtree searched whole before the next root, splitting a candidate into its four
    children one level down, best child first, and skipping any whose bound is not above
    the best finest score so far (``threshold`` at the start). With one lane this is
    Cartographer's search (`branch_and_bound`). With several, each lane keeps its own best:
    it prunes less, never more, so the first leaf of the highest score in the roots' order
    is found by the lane that owns its root (`branch_and_bound_lanes` merges). ``shared[j]``
    is lane ``j``'s best so far (``len(shared)`` lanes): a lane also skips what scores
    strictly below another lane's best, which can never win, but not what only ties it (a tie
    found earlier in the roots' order wins the merge).

    Returns:
        ``(k, dx, dy, best_sum, n_evaluated, found, t)``: ``t`` the position in ``order`` of
        the best leaf's root (-1 when none scored above ``threshold``).
    """
    top = levels - 1
    step = 1 << top
    m = (2 * w) // step + 1
    cap = 4 * levels + 4  # a subtree's stack: at most three siblings left per level
    sk = np.empty(cap, dtype=np.int32)
    sdx = np.empty(cap, dtype=np.int32)
    sdy = np.empty(cap, dtype=np.int32)
    sh = np.empty(cap, dtype=np.int32)
    ss = np.empty(cap, dtype=np.float64)
    best = threshold
    bk = 0
    bdx = 0
    bdy = 0
    bt = -1
    found = False
    n_eval = 0
    chk = np.empty(4, dtype=np.int32)
    chx = np.empty(4, dtype=np.int32)
    chy = np.empty(4, dtype=np.int32)
    chs = np.empty(4, dtype=np.float64)
    n_top = order.shape[0]
    lanes = shared.shape[0]
    for t in range(n_top - 1, -1, -1):
        if (n_top - 1 - t) % lanes != lane:
            continue
        o = order[t]
        if cs[o] <= best or cs[o] < _others(shared, lane):
            continue
        sk[0] = o // (m * m)
        sdx[0] = -w + ((o // m) % m) * step
        sdy[0] = -w + (o % m) * step
        sh[0] = top
        ss[0] = cs[o]
        sp = 1
        while sp > 0:
            sp -= 1
            if ss[sp] <= best or (lanes > 1 and ss[sp] < _others(shared, lane)):
                continue
            k = sk[sp]
            h = sh[sp]
            if ex_r2 >= 0.0 and _block_excluded(sdx[sp], sdy[sp], h, ex_dx, ex_dy, ex_r2):
                continue
            if h == 0:
                best = ss[sp]
                bk = k
                bdx = sdx[sp]
                bdy = sdy[sp]
                bt = t
                found = True
                shared[lane] = best  # another thread may read a stale value: it prunes less
                continue
            half = 1 << (h - 1)
            # the four children in one pass over the runs (one beyond the window is summed
            # too, and dropped here)
            four = _sum_children(stack[h - 1], pad, ix, iy, wt, count[k], k, sdx[sp], sdy[sp], half)
            nc = 0
            for q in range(4):
                dx = sdx[sp] + (half if q & 1 else 0)
                dy = sdy[sp] + (half if q & 2 else 0)
                if dx > w or dy > w:
                    continue
                s = four[q]
                n_eval += 1
                if s > best:
                    # insertion sort, ascending, of at most four children
                    j = nc
                    while j > 0 and chs[j - 1] > s:
                        chk[j] = chk[j - 1]
                        chx[j] = chx[j - 1]
                        chy[j] = chy[j - 1]
                        chs[j] = chs[j - 1]
                        j -= 1
                    chk[j] = k
                    chx[j] = dx
                    chy[j] = dy
                    chs[j] = s
                    nc += 1
            for q in range(nc):
                sk[sp] = chk[q]
                sdx[sp] = chx[q]
                sdy[sp] = chy[q]
                sh[sp] = h - 1
                ss[sp] = chs[q]
                sp += 1
    return bk, bdx, bdy, best, n_eval, found, bt


@njit(cache=True, error_model="numpy", nogil=True)
def branch_and_bound(
    stack: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    wt: NDArray[np.float64],
    count: NDArray[np.int64],
    w: int,
    levels: int,
    threshold: float,
    ex_dx: int = 0,
    ex_dy: int = 0,
    ex_r2: float = -1.0,
) -> tuple[int, int, int, float, int, bool]:
    """Best ``(k, dx, dy)`` with ``|dx|, |dy| <= w`` over all angles, by branch-and-bound.

    With ``ex_r2 >= 0`` the offsets within ``sqrt(ex_r2)`` cells of ``(ex_dx, ex_dy)`` are
    left out (at any angle): the best pose *elsewhere*, a second peak of the response. A
    candidate whose whole block lies in that disc is pruned, one that straddles it is split
    as usual, so the result is the exact best outside the disc.

    Cartographer's fast correlative matcher (Hess et al. 2016, Sec. V.C): every candidate of
    the coarsest level ``levels - 1`` is scored (`top_sums`) and sorted, then each is
    searched depth first, best first (`descend`, one lane). ``ix, iy, wt, count`` are the
    merged runs of the points (`discretise_runs`).

    Returns:
        ``(k, dx, dy, best_sum, n_evaluated, found)``; ``found`` is False when no finest
        candidate scored above ``threshold``.
    """
    step = 1 << (levels - 1)
    m = (2 * w) // step + 1
    k_n = ix.shape[0]
    cs = np.empty(k_n * m * m, dtype=np.float64)
    top_sums(stack, pad, ix, iy, wt, count, w, levels, 0, k_n, cs)
    order = sort_order(cs)
    lane = np.full(1, -np.inf)
    k, dx, dy, best, n_eval, found, _ = descend(
        stack, pad, ix, iy, wt, count, w, levels, threshold, ex_dx, ex_dy, ex_r2, cs, order, 0,
        lane,
    )  # fmt: skip
    return k, dx, dy, best, n_eval + k_n * m * m, found


@njit(cache=True, error_model="numpy", nogil=True)
def brute_force(
    stack: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    w: int,
) -> tuple[int, int, int, float, int]:
    """Exhaustive search of every finest ``(k, dx, dy)`` (the baseline of tests and benchmarks).

    Returns:
        ``(k, dx, dy, best_sum, n_evaluated)``; the first maximum in (k, dx, dy) order.
    """
    lvl = stack[0]
    best = -1.0
    bk = 0
    bdx = 0
    bdy = 0
    n = 0
    for k in range(ix.shape[0]):
        for dx in range(-w, w + 1):
            for dy in range(-w, w + 1):
                s = _sum_at(lvl, pad, ix, iy, k, dx, dy)
                n += 1
                if s > best:
                    best = s
                    bk = k
                    bdx = dx
                    bdy = dy
    return bk, bdx, bdy, best, n


@njit(cache=True, error_model="numpy", nogil=True)
def neighbourhood(
    stack: NDArray[np.float32],
    pad: int,
    ix: NDArray[np.int32],
    iy: NDArray[np.int32],
    wt: NDArray[np.float64],
    count: NDArray[np.int64],
    dx0: int,
    dy0: int,
    half: int,
) -> NDArray[np.float64]:
    """Finest-level sums ``(len(angles), 2 half + 1, 2 half + 1)`` around ``(dx0, dy0)``.

    ``out[k, a, b]`` is the sum at offset ``(dx0 + a - half, dy0 + b - half)`` over the merged
    runs (`discretise_runs`) of rotation ``k``: the per-point sum, exactly (module docstring).
    """
    lvl = stack[0]
    side = 2 * half + 1
    out = np.empty((ix.shape[0], side, side), dtype=np.float64)
    sums = np.empty(side * side)
    for k in range(ix.shape[0]):
        _lattice_sums(lvl, pad, ix, iy, wt, count[k], k, dx0 - half, dy0 - half, side, 1, sums)
        for a in range(side):
            for b in range(side):
                out[k, a, b] = sums[a * side + b]
    return out


@njit(cache=True, error_model="numpy", nogil=True)
def score_pose(
    table: NDArray[np.float32],
    src: NDArray[np.float64],
    px: float,
    py: float,
    pth: float,
    x0: float,
    y0: float,
    res: float,
) -> float:
    """Sum of level-0 table values at the source points under one pose (0 off the table)."""
    ny, nx = table.shape
    c = math.cos(pth)
    s = math.sin(pth)
    inv = 1.0 / res
    total = 0.0
    for p in range(src.shape[0]):
        qx = c * src[p, 0] - s * src[p, 1] + px
        qy = s * src[p, 0] + c * src[p, 1] + py
        fx = math.floor((qx - x0) * inv)
        fy = math.floor((qy - y0) * inv)
        if 0.0 <= fx < nx and 0.0 <= fy < ny:
            total += table[int(fy), int(fx)]
    return total
