"""Numba kernels of the GMapping back end: map cells, scan score and likelihood.

Cell layout, the scan score and likelihood, hill climbing and the improved proposal's sample
grid; the registration of scans into the copy-on-write patches is in `_register`.

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
from collections.abc import Iterator
from contextlib import contextmanager

import numba
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


@contextmanager
def one_particle_chunks() -> Iterator[None]:
    """Parallel kernels launched inside hand their ``prange`` iterations out one at a time.

    Particles differ in cost (1-3 ms of matching on FR079) and a loaded machine stalls one
    thread or the other, so a static split in halves leaves a core idle. Set from Python: a
    kernel that set it itself could not be cached by numba.
    """
    old = numba.set_parallel_chunksize(1)
    try:
        yield
    finally:
        numba.set_parallel_chunksize(old)


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


#: Cell flag: occupied for the matcher (``hits > fullness * visits``, a candidate beam end).
OCC = np.uint8(1)
#: Cell flag: occupied for the free-cell probe (``visits > 0`` and ``hits >= fullness *
#: visits``; OpenSLAM tests ``>=`` there and ``>`` for the candidate, so the two differ).
PROBE = np.uint8(2)


@njit(cache=True, inline="always")
def cell_flags(h: int, v: int) -> np.uint8:
    """`OCC` | `PROBE` of a cell with ``h`` hits and ``v`` visits.

    The comparisons are written exactly as OpenSLAM's (``FULLNESS * v`` in float64), so the
    flags reproduce its tests bit for bit.
    """
    if v == 0:
        return np.uint8(0)
    f = np.uint8(0)
    if h > FULLNESS * v:
        f |= OCC
    if h >= FULLNESS * v:
        f |= PROBE
    return f


@njit(cache=True)
def usable_beams(ranges: NDArray[np.float64], usable: float, lskip: int) -> NDArray[np.int64]:
    """Indices of the beams the matcher uses (OpenSLAM's skip counter and range test).

    Beams 0, lskip+1, 2(lskip+1), ... that are positive and no longer than ``usable``;
    computed once per scan instead of once per pose evaluation.
    """
    out = np.empty(ranges.shape[0], dtype=np.int64)
    n = 0
    skip = 0
    for j in range(ranges.shape[0]):
        skip += 1
        if skip > lskip:
            skip = 0
        r = ranges[j]
        if skip != 0 or not (r <= usable) or r <= 0.0:
            continue
        out[n] = j
        n += 1
    return out[:n]


@njit(cache=True, error_model="numpy", inline="always")
def _window(
    table: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    ox: float,
    oy: float,
    delta: float,
    hcx: int,
    hcy: int,
    fcx: int,
    fcy: int,
    kernel: int,
    out: NDArray[np.float64],
) -> int:
    """Candidate cell means of one beam end: writes ``(x, y)`` rows into ``out``, returns count.

    A candidate is an `OCC` cell of the ``(2k+1)^2`` window around ``(hcx, hcy)`` whose free
    probe ``(cx + fcx, cy + fcy)`` is not `PROBE` (unknown or outside counts as free). The
    mean is computed exactly as OpenSLAM's ``PointAccumulator::mean``.
    """
    m = 0
    for xx in range(-kernel, kernel + 1):
        for yy in range(-kernel, kernel + 1):
            cx = hcx + xx
            cy = hcy + yy
            pid, k = _cell_ref(table, cx, cy)
            if pid < 0 or not (flags[pid, k] & OCC):
                continue
            fpid, fk = _cell_ref(table, cx + fcx, cy + fcy)
            if fpid >= 0 and flags[fpid, fk] & PROBE:
                continue
            n = hits[pid, k]
            out[m, 0] = ox + (cx + 0.5) * delta + accx[pid, k] / n
            out[m, 1] = oy + (cy + 0.5) * delta + accy[pid, k] / n
            m += 1
    return m


#: Initial window cache slots per usable beam (a power of two is taken above it): one
#: particle's whole matching on FR079 (~100 pose evaluations x 360 beams) mostly searches
#: 1300-3300 distinct windows, and 12 bytes per slot (~100 KB at 360 beams) still sit in a
#: core's L2 cache; `_grown` doubles the table for the matchings that search more.
CACHE_SLOTS_PER_BEAM = 16
#: Offset and bit width of an end cell coordinate in a packed cache key (cells beyond +-2^26,
#: 3000 km at 5 cm, are searched uncached).
_KEY_OFF = 1 << 26
_KEY_BITS = 27
#: Most candidates of one window + 1 (``(2 * 10 + 1)^2 = 441`` at the largest kernelSize).
_COUNT_BITS = 9
_COUNT_RANGE = 1 << _COUNT_BITS
#: 2^64 / golden ratio as a signed int64 (an unsigned literal would make numba mix int64 and
#: uint64, which it does in float64).
_HASH_MUL = -7046029254386353131


@njit(cache=True)
def _scratch(
    n_beams: int, kernel: int
) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.float64]]:
    """An empty window cache for `_score_pose`: ``(keys (S + 2,), vals (S,), pool (C + W, 2))``.

    ``keys[h]`` is a packed (end cell, probe offset) key (-1: empty slot), ``vals[h]`` the
    ``start * 512 + count`` of its candidates in ``pool``; ``keys[S]`` and ``keys[S + 1]`` count
    the used slots and pool rows (one array fewer to pass through every call). The last ``W``
    rows of ``pool`` are the scratch of a window that is not cached.
    """
    s = 1
    while s < CACHE_SLOTS_PER_BEAM * max(n_beams, 1):
        s *= 2
    keys = np.full(s + 2, -1, dtype=np.int64)
    keys[s] = 0
    keys[s + 1] = 0
    w = (2 * kernel + 1) ** 2
    # ~1 candidate per window on average: 2 rows per slot and a half-full table leave room
    return keys, np.empty(s, dtype=np.int32), np.empty((2 * s + w, 2))


@njit(cache=True)
def _grown(
    keys: NDArray[np.int64], vals: NDArray[np.int32], pool: NDArray[np.float64], kernel: int
) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.float64]]:
    """The window cache, doubled (rehashed) past a quarter load or with a half-full pool.

    Called between pose evaluations, so that a matching that wanders over many cells keeps
    caching instead of falling back to uncached searches at half load. Candidate rows keep
    their place (the pool only grows at the end), so the values need no rewrite.
    """
    s = vals.shape[0]
    used = keys[s]
    rows = keys[s + 1]
    w = (2 * kernel + 1) ** 2
    if 4 * used > s:
        s2 = 2 * s
        nk = np.full(s2 + 2, -1, dtype=np.int64)
        nv = np.empty(s2, dtype=np.int32)
        for h in range(s):
            key = keys[h]
            if key < 0:
                continue
            g = ((key * _HASH_MUL) >> 40) & (s2 - 1)
            while nk[g] >= 0:
                g = (g + 1) & (s2 - 1)
            nk[g] = key
            nv[g] = vals[h]
        nk[s2] = used
        nk[s2 + 1] = rows
        keys, vals = nk, nv
    if 2 * (rows + w) > pool.shape[0] - w:
        np_ = np.empty((2 * pool.shape[0], 2))
        np_[:rows] = pool[:rows]
        pool = np_
    return keys, vals, pool


@njit(cache=True, error_model="numpy")
def _fill_window(
    table: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    ox: float,
    oy: float,
    delta: float,
    hcx: int,
    hcy: int,
    fcx: int,
    fcy: int,
    key: int,
    slot: int,
    kernel: int,
    keys: NDArray[np.int64],
    vals: NDArray[np.int32],
    pool: NDArray[np.float64],
) -> tuple[int, int]:
    """Search the window of a key missing from the cache and store it in ``slot``.

    Returns ``(start, count)`` of its candidates in ``pool``. With ``slot < 0`` (a key that
    cannot be packed), at half load or with a full pool, the window is searched into the
    scratch rows instead (exact, just not cached). Kept out of line: it runs once per distinct
    key, and inlined it would bloat the per-beam loop of `_score_pose`.
    """
    s = vals.shape[0]
    w = (2 * kernel + 1) ** 2
    used = keys[s]
    rows = keys[s + 1]
    scratch = pool.shape[0] - w
    if slot < 0 or 2 * (used + 1) > s or rows + w > scratch:
        m = _window(table, flags, hits, accx, accy, ox, oy, delta, hcx, hcy, fcx, fcy, kernel,
                    pool[scratch:])  # fmt: skip
        return scratch, m
    m = _window(table, flags, hits, accx, accy, ox, oy, delta, hcx, hcy, fcx, fcy, kernel,
                pool[rows:])  # fmt: skip
    keys[slot] = key
    vals[slot] = rows * _COUNT_RANGE + m
    keys[s] = used + 1
    keys[s + 1] = rows + m
    return rows, m


@njit(cache=True, error_model="numpy")
def _score_pose(
    table: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
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
    beams: NDArray[np.int64],
    kernel: int,
    sigma: float,
    lsigma: float,
    keys: NDArray[np.int64],
    vals: NDArray[np.int32],
    pool: NDArray[np.float64],
) -> tuple[float, float, int]:
    """GMapping's ``likelihoodAndScore`` of one pose: (score, log-likelihood, beams found).

    For each beam end, the closest cell mean among the occupied cells of the (2k+1)^2 window
    whose "free" probe (one cell back along the beam) is not occupied; score adds
    ``exp(-d^2/sigma)``, the likelihood ``-d^2/lsigma`` or ``nullLikelihood/lsigma`` if none.

    The candidates of a window come from the cache ``keys, vals, pool`` (`_scratch`): on
    FR079 one particle's ~100 pose evaluations x 360 beams end in ~1000 distinct cells, so
    nearly every window is searched once per particle instead of once per beam and pose. The
    minimum over the same candidates is the same number whatever their order, so the result is
    bit-identical to OpenSLAM's per-beam search.
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
    mask = vals.shape[0] - 1
    score = 0.0
    loglik = 0.0
    found_n = 0
    for b in range(beams.shape[0]):
        j = beams[b]
        r = ranges[j]
        dc = lc * ca[j] - ls * sa[j]
        ds = ls * ca[j] + lc * sa[j]
        hx = lx + r * dc
        hy = ly + r * ds
        hcx = math.floor((hx - ox) * inv)
        hcy = math.floor((hy - oy) * inv)
        fcx = math.floor((hx - free_d * dc - ox) * inv) - hcx
        fcy = math.floor((hy - free_d * ds - oy) * inv) - hcy
        # the cache lookup is written out here (open addressing, linear probing): a call per
        # beam would pass every array by value and cost more than the search it saves
        px = hcx + _KEY_OFF
        py = hcy + _KEY_OFF
        if 0 <= px < (1 << _KEY_BITS) and 0 <= py < (1 << _KEY_BITS):
            # probe offsets are a few cells: 4 bits each
            key = (px << (_KEY_BITS + 8)) | (py << 8) | ((fcx + 8) << 4) | (fcy + 8)
            # Fibonacci hashing; the int64 product wraps, which numba does without a check
            h = ((key * _HASH_MUL) >> 40) & mask
            while True:
                kh = keys[h]
                if kh == key:
                    v = vals[h]
                    start = v >> _COUNT_BITS
                    m = v & (_COUNT_RANGE - 1)
                    break
                if kh < 0:
                    start, m = _fill_window(
                        table, flags, hits, accx, accy, ox, oy, delta, hcx, hcy, fcx, fcy,
                        key, h, kernel, keys, vals, pool,
                    )  # fmt: skip
                    break
                h = (h + 1) & mask
        else:
            start, m = _fill_window(
                table, flags, hits, accx, accy, ox, oy, delta, hcx, hcy, fcx, fcy, -1, -1,
                kernel, keys, vals, pool,
            )  # fmt: skip
        # min() rather than a compare-and-branch per candidate, and "found" is "any candidate"
        # (a squared distance is finite, below the 1e300 start): both compile without
        # branches the predictor would miss on
        best = 1e300
        for q in range(start, start + m):
            best = min(best, (hx - pool[q, 0]) ** 2 + (hy - pool[q, 1]) ** 2)
        if m > 0:
            score += math.exp(-best / sigma)
            loglik += -best / lsigma
            found_n += 1
        else:
            loglik += no_hit
    return score, loglik, found_n


@njit(cache=True, error_model="numpy")
def _optimize(
    table: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
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
    beams: NDArray[np.int64],
    kernel: int,
    sigma: float,
    lsigma: float,
    lstep: float,
    astep: float,
    iterations: int,
    keys: NDArray[np.int64],
    vals: NDArray[np.int32],
    pool: NDArray[np.float64],
) -> tuple[
    float, float, float, float, float, NDArray[np.int64], NDArray[np.int32], NDArray[np.float64]
]:
    """OpenSLAM's ``ScanMatcher::optimize``: greedy hill climbing in world x, y, theta.

    Six moves per round (+-x, +-y, +-theta); a round without improvement halves both steps,
    and the search stops after ``iterations`` halvings without improvement. Returns
    ``(x, y, theta, best score, log-likelihood there)`` and the window cache (`_grown`).
    """
    cx, cy, ct = init[0], init[1], init[2]
    cur, cur_l, _ = _score_pose(
        table, flags, hits, accx, accy, ox, oy, delta, cx, cy, ct, lo, ranges, ca, sa, beams,
        kernel, sigma, lsigma, keys, vals, pool,
    )  # fmt: skip
    # the previous centre: after a move, the opposite move of the next round usually lands on
    # it bit for bit ((x + d) - d == x), and the score of a pose is a pure function of it
    px, py, pt, p_sc, p_l = math.nan, math.nan, math.nan, 0.0, 0.0
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
        bx, by, bt, b_l = cx, cy, ct, cur_l
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
            if x == px and y == py and t == pt:
                sc, lk = p_sc, p_l
            else:
                sc, lk, _ = _score_pose(
                    table, flags, hits, accx, accy, ox, oy, delta, x, y, t, lo, ranges, ca, sa,
                    beams, kernel, sigma, lsigma, keys, vals, pool,
                )  # fmt: skip
                keys, vals, pool = _grown(keys, vals, pool, kernel)
            if sc > cur:
                cur = sc
                bx, by, bt, b_l = x, y, t, lk
        if bx != cx or by != cy or bt != ct:
            px, py, pt, p_sc, p_l = cx, cy, ct, best, cur_l
        cx, cy, ct, cur_l = bx, by, bt, b_l
        if not (cur > best or refinement < iterations):
            break
    return cx, cy, ct, best, cur_l, keys, vals, pool


@njit(cache=True, error_model="numpy", parallel=True)
def match_particles(  # noqa: D417 (the map and scan arguments are those of `_score_pose`)
    tables: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
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
        flags: `cell_flags` of every cell of the pool (kept by `_register.register_particles`).
        usable: Beams longer than this are not used.
        lskip: Use one beam in ``lskip + 1``.
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
    beams = usable_beams(ranges, usable, lskip)
    # one particle per iteration: no shared writes, and the result does not depend on the
    # thread count or on which thread runs which particle (each particle's computation is
    # serial, with its own window cache; the caller hands particles out one at a time:
    # `one_particle_chunks`)
    for i in prange(n):
        tb = tables[i]
        keys, vals, pool = _scratch(beams.shape[0], kernel)
        x, y, t, sc, lk, keys, vals, pool = _optimize(
            tb, flags, hits, accx, accy, ox, oy, delta, poses[i], lo, ranges, ca, sa, beams,
            kernel, sigma, lsigma, lstep, astep, iterations, keys, vals, pool,
        )  # fmt: skip
        modes[i, 0] = x
        modes[i, 1] = y
        modes[i, 2] = t
        scores[i] = sc
        # the hill climber scored the mode already (same pose, same numbers)
        lmode[i] = lk
        for k in range(grid.shape[0]):
            if grid[k, 0] == 0.0 and grid[k, 1] == 0.0 and grid[k, 2] == 0.0:
                lgrid[i, k] = lk
                continue
            lgrid[i, k] = _score_pose(
                tb, flags, hits, accx, accy, ox, oy, delta, x + grid[k, 0], y + grid[k, 1],
                t + grid[k, 2], lo, ranges, ca, sa, beams, kernel, sigma, lsigma, keys, vals, pool,
            )[1]  # fmt: skip
            keys, vals, pool = _grown(keys, vals, pool, kernel)
    return modes, scores, lmode, lgrid


@njit(cache=True, error_model="numpy", parallel=True)
def grid_particles(
    tables: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
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
    beams = usable_beams(ranges, usable, lskip)
    for i in prange(poses.shape[0]):
        keys, vals, pool = _scratch(beams.shape[0], kernel)
        for k in range(grid.shape[0]):
            out[i, k] = _score_pose(
                tables[i], flags, hits, accx, accy, ox, oy, delta, poses[i, 0] + grid[k, 0],
                poses[i, 1] + grid[k, 1], poses[i, 2] + grid[k, 2], lo, ranges, ca, sa, beams,
                kernel, sigma, lsigma, keys, vals, pool,
            )[1]  # fmt: skip
            keys, vals, pool = _grown(keys, vals, pool, kernel)
    return out
