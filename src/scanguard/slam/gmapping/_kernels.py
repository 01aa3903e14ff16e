"""Numba kernels of the GMapping back end.

Map cells, scan score and likelihood, hill climbing, the improved proposal's sample grid, and
scan registration with copy-on-write patches.

The particles' maps live in one pool of fixed-size patches (``PATCH`` x ``PATCH`` cells). Each
particle owns a table of patch ids (``-1``: never observed, every cell unknown); particles that
share an ancestor share its patches until one of them writes (copy-on-write, reference
counts). This is what OpenSLAM's ``HierarchicalArray2D`` with shared ``autoptr`` patches does.

A cell is GMapping's ``PointAccumulator``: ``hits`` (beams that ended in it), ``visits`` (beams
that ended in or passed through it) and the sum of the hit points, kept as float32 offsets from
the cell centre (bounded, so the sum stays exact to ~1e-5 m even after 10^4 hits, which world
coordinates in float32 would not).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

#: Patch side as a power of two, so that cell -> patch is a shift and a mask.
PATCH_BITS = 4
PATCH = 1 << PATCH_BITS
PATCH_MASK = PATCH - 1
PATCH_CELLS = PATCH * PATCH

#: Hit ratio above which a cell counts as occupied for matching (OpenSLAM's
#: ``fullnessThreshold``).
FULLNESS = 0.1
#: OpenSLAM's ``nullLikelihood``: log-likelihood of a beam whose end finds no occupied cell.
NULL_LIKELIHOOD = -0.5
#: Free-cell probe distance in cells (OpenSLAM's ``freeCellRatio``).
FREE_CELL_RATIO = math.sqrt(2.0)


@njit(cache=True, inline="always")
def _cell_ref(table: NDArray[np.int32], cx: int, cy: int) -> tuple[int, int]:
    """(patch id, cell index inside the patch); patch id -1 for unknown or outside."""
    if cx < 0 or cy < 0:
        return -1, 0
    px = cx >> PATCH_BITS
    py = cy >> PATCH_BITS
    if py >= table.shape[0] or px >= table.shape[1]:
        return -1, 0
    return table[py, px], ((cy & PATCH_MASK) << PATCH_BITS) | (cx & PATCH_MASK)


@njit(cache=True, error_model="numpy")
def _score_pose(
    table: NDArray[np.int32],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    ox: float,
    oy: float,
    delta: float,
    x: float,
    y: float,
    th: float,
    lo: NDArray[np.float64],
    ranges: NDArray[np.float64],
    ca: NDArray[np.float64],
    sa: NDArray[np.float64],
    usable: float,
    kernel: int,
    lskip: int,
    sigma: float,
    lsigma: float,
) -> tuple[float, float, int]:
    """GMapping's ``likelihoodAndScore`` of one pose: (score, log-likelihood, beams found).

    For each beam end, the closest cell mean among the occupied cells of the (2k+1)^2 window
    whose "free" probe (one cell back along the beam) is not occupied; score adds
    ``exp(-d^2/sigma)``, the likelihood ``-d^2/lsigma`` or ``nullLikelihood/lsigma`` if none.
    """
    c = math.cos(th)
    s = math.sin(th)
    lx = x + c * lo[0] - s * lo[1]
    ly = y + s * lo[0] + c * lo[1]
    lc = math.cos(th + lo[2])
    ls = math.sin(th + lo[2])
    inv = 1.0 / delta
    no_hit = NULL_LIKELIHOOD / lsigma
    free_d = FREE_CELL_RATIO * delta
    score = 0.0
    loglik = 0.0
    found_n = 0
    skip = 0
    for j in range(ranges.shape[0]):
        # OpenSLAM's skip counter: beams 0, lskip+1, 2(lskip+1), ... are used
        skip += 1
        if skip > lskip:
            skip = 0
        r = ranges[j]
        if skip != 0 or not (r <= usable) or r <= 0.0:
            continue
        dc = lc * ca[j] - ls * sa[j]
        ds = ls * ca[j] + lc * sa[j]
        hx = lx + r * dc
        hy = ly + r * ds
        hcx = math.floor((hx - ox) * inv)
        hcy = math.floor((hy - oy) * inv)
        fcx = math.floor((hx - free_d * dc - ox) * inv) - hcx
        fcy = math.floor((hy - free_d * ds - oy) * inv) - hcy
        best = 1e300
        found = False
        for xx in range(-kernel, kernel + 1):
            for yy in range(-kernel, kernel + 1):
                cx = hcx + xx
                cy = hcy + yy
                pid, k = _cell_ref(table, cx, cy)
                if pid < 0:
                    continue
                v = visits[pid, k]
                if v == 0 or hits[pid, k] <= FULLNESS * v:
                    continue
                fpid, fk = _cell_ref(table, cx + fcx, cy + fcy)
                if fpid >= 0:
                    fv = visits[fpid, fk]
                    if fv > 0 and hits[fpid, fk] >= FULLNESS * fv:
                        continue
                n = hits[pid, k]
                mx = ox + (cx + 0.5) * delta + accx[pid, k] / n
                my = oy + (cy + 0.5) * delta + accy[pid, k] / n
                d2 = (hx - mx) ** 2 + (hy - my) ** 2
                if d2 < best:
                    best = d2
                    found = True
        if found:
            score += math.exp(-best / sigma)
            loglik += -best / lsigma
            found_n += 1
        else:
            loglik += no_hit
    return score, loglik, found_n


@njit(cache=True, error_model="numpy")
def _optimize(
    table: NDArray[np.int32],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    ox: float,
    oy: float,
    delta: float,
    init: NDArray[np.float64],
    lo: NDArray[np.float64],
    ranges: NDArray[np.float64],
    ca: NDArray[np.float64],
    sa: NDArray[np.float64],
    usable: float,
    kernel: int,
    lskip: int,
    sigma: float,
    lsigma: float,
    lstep: float,
    astep: float,
    iterations: int,
) -> tuple[float, float, float, float]:
    """OpenSLAM's ``ScanMatcher::optimize``: greedy hill climbing in world x, y, theta.

    Six moves per round (+-x, +-y, +-theta); a round without improvement halves both steps,
    and the search stops after ``iterations`` halvings without improvement. Returns
    ``(x, y, theta, best score)``.
    """
    cx, cy, ct = init[0], init[1], init[2]
    cur = _score_pose(
        table, hits, visits, accx, accy, ox, oy, delta, cx, cy, ct, lo, ranges, ca, sa,
        usable, kernel, lskip, sigma, lsigma,
    )[0]  # fmt: skip
    best = -1.0
    ld = lstep
    ad = astep
    refinement = 0
    while True:
        if best >= cur:
            refinement += 1
            ld *= 0.5
            ad *= 0.5
        best = cur
        bx, by, bt = cx, cy, ct
        for move in range(6):
            x, y, t = cx, cy, ct
            if move == 0:
                x += ld
            elif move == 1:
                x -= ld
            elif move == 2:
                y -= ld
            elif move == 3:
                y += ld
            elif move == 4:
                t += ad
            else:
                t -= ad
            sc = _score_pose(
                table, hits, visits, accx, accy, ox, oy, delta, x, y, t, lo, ranges, ca, sa,
                usable, kernel, lskip, sigma, lsigma,
            )[0]  # fmt: skip
            if sc > cur:
                cur = sc
                bx, by, bt = x, y, t
        cx, cy, ct = bx, by, bt
        if not (cur > best or refinement < iterations):
            break
    return cx, cy, ct, best


@njit(cache=True, error_model="numpy", parallel=True)
def match_particles(  # noqa: D417 (the map and scan arguments are those of `_score_pose`)
    tables: NDArray[np.int32],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    ox: float,
    oy: float,
    delta: float,
    poses: NDArray[np.float64],
    lo: NDArray[np.float64],
    ranges: NDArray[np.float64],
    ca: NDArray[np.float64],
    sa: NDArray[np.float64],
    usable: float,
    kernel: int,
    lskip: int,
    sigma: float,
    lsigma: float,
    lstep: float,
    astep: float,
    iterations: int,
    grid: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Scan-match every particle against its own map (read only, so particles run in parallel).

    Args:
        grid: ``(K, 3)`` offsets around each particle's mode at which the likelihood is also
            evaluated (the improved proposal's samples; ``K = 0`` for none).

    Returns:
        ``(modes (P, 3), scores (P,), log-likelihood at the mode (P,), grid log-likelihoods
        (P, K))``.
    """
    n = poses.shape[0]
    modes = np.empty((n, 3))
    scores = np.empty(n)
    lmode = np.empty(n)
    lgrid = np.empty((n, grid.shape[0]))
    # one particle per iteration: no shared writes, and the result does not depend on the
    # thread count (each particle's computation is serial)
    for i in prange(n):
        tb = tables[i]
        x, y, t, sc = _optimize(
            tb, hits, visits, accx, accy, ox, oy, delta, poses[i], lo, ranges, ca, sa,
            usable, kernel, lskip, sigma, lsigma, lstep, astep, iterations,
        )  # fmt: skip
        modes[i, 0] = x
        modes[i, 1] = y
        modes[i, 2] = t
        scores[i] = sc
        lmode[i] = _score_pose(
            tb, hits, visits, accx, accy, ox, oy, delta, x, y, t, lo, ranges, ca, sa,
            usable, kernel, lskip, sigma, lsigma,
        )[1]  # fmt: skip
        for k in range(grid.shape[0]):
            lgrid[i, k] = _score_pose(
                tb, hits, visits, accx, accy, ox, oy, delta, x + grid[k, 0], y + grid[k, 1],
                t + grid[k, 2], lo, ranges, ca, sa, usable, kernel, lskip, sigma, lsigma,
            )[1]  # fmt: skip
    return modes, scores, lmode, lgrid


@njit(cache=True, inline="always")
def _writable(
    table: NDArray[np.int32],
    py: int,
    px: int,
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    refs: NDArray[np.int32],
    free: NDArray[np.int32],
    nfree: NDArray[np.int64],
) -> int:
    """Patch id of ``table[py, px]`` that this particle may write.

    A fresh zero patch for an unknown one, a private copy of a shared one (copy-on-write).
    """
    pid = table[py, px]
    if pid >= 0 and refs[pid] == 1:
        return pid
    nfree[0] -= 1
    new = free[nfree[0]]
    if pid < 0:
        for k in range(PATCH_CELLS):
            hits[new, k] = 0
            visits[new, k] = 0
            accx[new, k] = 0.0
            accy[new, k] = 0.0
    else:
        for k in range(PATCH_CELLS):
            hits[new, k] = hits[pid, k]
            visits[new, k] = visits[pid, k]
            accx[new, k] = accx[pid, k]
            accy[new, k] = accy[pid, k]
        refs[pid] -= 1
    refs[new] = 1
    table[py, px] = new
    return new


@njit(cache=True, error_model="numpy")
def register_scan(
    table: NDArray[np.int32],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    refs: NDArray[np.int32],
    free: NDArray[np.int32],
    nfree: NDArray[np.int64],
    ox: float,
    oy: float,
    delta: float,
    pose: NDArray[np.float64],
    lo: NDArray[np.float64],
    ranges: NDArray[np.float64],
    ca: NDArray[np.float64],
    sa: NDArray[np.float64],
    usable: float,
    max_range: float,
    start: int,
    reserve: int,
) -> int:
    """OpenSLAM's ``registerScan`` into one particle's map, from beam ``start`` on.

    Each beam no longer than ``max_range`` marks the cells it passes through as visited; a beam
    no longer than ``usable`` also adds a hit (and the hit point) to its end cell, a longer one
    is cut at ``usable`` and its end cell is left alone.

    Returns:
        ``-1`` when done, or the beam index to resume from once the caller has refilled the
        free-patch stack: a beam starts only while at least ``reserve`` free patches remain
        (the most one beam can need), so no beam is ever half registered.
    """
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    lx = pose[0] + c * lo[0] - s * lo[1]
    ly = pose[1] + s * lo[0] + c * lo[1]
    lc = math.cos(pose[2] + lo[2])
    ls = math.sin(pose[2] + lo[2])
    inv = 1.0 / delta
    x0 = math.floor((lx - ox) * inv)
    y0 = math.floor((ly - oy) * inv)
    ny = table.shape[0] << PATCH_BITS
    nx = table.shape[1] << PATCH_BITS
    for j in range(start, ranges.shape[0]):
        r = ranges[j]
        if not (r <= max_range) or r <= 0.0:
            continue
        if nfree[0] < reserve:
            return j
        cropped = r > usable
        d = usable if cropped else r
        dc = lc * ca[j] - ls * sa[j]
        ds = ls * ca[j] + lc * sa[j]
        hx = lx + d * dc
        hy = ly + d * ds
        x1 = math.floor((hx - ox) * inv)
        y1 = math.floor((hy - oy) * inv)
        # Bresenham from the laser cell to the end cell; every cell but the last is free
        dx = abs(x1 - x0)
        dy = -abs(y1 - y0)
        sx = 1 if x0 < x1 else -1
        sy = 1 if y0 < y1 else -1
        err = dx + dy
        x = x0
        y = y0
        while True:
            last = x == x1 and y == y1
            if 0 <= x < nx and 0 <= y < ny and not (last and cropped):
                pid = _writable(
                    table, y >> PATCH_BITS, x >> PATCH_BITS, hits, visits, accx, accy, refs,
                    free, nfree,
                )  # fmt: skip
                k = ((y & PATCH_MASK) << PATCH_BITS) | (x & PATCH_MASK)
                visits[pid, k] += 1
                if last:
                    hits[pid, k] += 1
                    accx[pid, k] += np.float32(hx - (ox + (x + 0.5) * delta))
                    accy[pid, k] += np.float32(hy - (oy + (y + 0.5) * delta))
            if last:
                break
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                x += sx
            if e2 <= dx:
                err += dx
                y += sy
    return -1


@njit(cache=True)
def retain_tables(tables: NDArray[np.int32], refs: NDArray[np.int32]) -> None:
    """Add one reference for every patch the given tables point to."""
    flat = tables.reshape(-1)
    for k in range(flat.shape[0]):
        pid = flat[k]
        if pid >= 0:
            refs[pid] += 1


@njit(cache=True)
def release_tables(
    tables: NDArray[np.int32],
    refs: NDArray[np.int32],
    free: NDArray[np.int32],
    nfree: NDArray[np.int64],
) -> None:
    """Drop one reference for every patch the tables point to; free the unreferenced ones."""
    flat = tables.reshape(-1)
    for k in range(flat.shape[0]):
        pid = flat[k]
        if pid >= 0:
            refs[pid] -= 1
            if refs[pid] == 0:
                free[nfree[0]] = pid
                nfree[0] += 1


@njit(cache=True, error_model="numpy", parallel=True)
def grid_particles(
    tables: NDArray[np.int32],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    ox: float,
    oy: float,
    delta: float,
    poses: NDArray[np.float64],
    lo: NDArray[np.float64],
    ranges: NDArray[np.float64],
    ca: NDArray[np.float64],
    sa: NDArray[np.float64],
    usable: float,
    kernel: int,
    lskip: int,
    sigma: float,
    lsigma: float,
    grid: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Log-likelihoods ``(P, K)`` at ``poses[i] + grid[k]`` (no matching)."""
    out = np.empty((poses.shape[0], grid.shape[0]))
    for i in prange(poses.shape[0]):
        for k in range(grid.shape[0]):
            out[i, k] = _score_pose(
                tables[i], hits, visits, accx, accy, ox, oy, delta, poses[i, 0] + grid[k, 0],
                poses[i, 1] + grid[k, 1], poses[i, 2] + grid[k, 2], lo, ranges, ca, sa, usable,
                kernel, lskip, sigma, lsigma,
            )[1]  # fmt: skip
    return out
