"""Numba kernels that write the GMapping maps: scan registration and patch reference counts.

Layout of the pool and the tables: see `_kernels`. All particles register one scan in one
parallel kernel (`register_particles`). Writes stay race-free and the maps do not depend on the
thread count because

* a particle writes only into patches it owns alone: a patch it shares (reference count above
  one) or has never observed is first replaced, in its own table, by a fresh patch taken from
  the block of free ids reserved for that particle (copy-on-write);
* reference counts are not changed during the parallel part: the shared patches a particle
  copied are listed, and their counts dropped (and the patches freed at zero) afterwards, in
  particle order (`release_copied`).

The difference from the serial registration of OpenSLAM: when the last particles sharing a
patch all write into it, each takes a copy (serially the last one would write in place) and the
original is freed right after. The cell values are the same; only patch ids and the pool's peak
occupancy differ.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from scanguard.slam.gmapping._kernels import PATCH_BITS, PATCH_CELLS, PATCH_MASK, cell_flags


@njit(cache=True, inline="always")
def _own_patch(
    table: NDArray[np.int32],
    py: int,
    px: int,
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    refs: NDArray[np.int32],
    block: NDArray[np.int32],
    left: NDArray[np.int64],
    copied: NDArray[np.int32],
    i: int,
) -> int:
    """Patch id of ``table[py, px]`` that particle ``i`` may write (copy-on-write).

    A fresh zero patch for an unknown one, a private copy of a shared one (its id is listed
    in ``copied[i]``; ``copied[i, 0]`` counts them). New ids come from the end of ``block``;
    ``left[i]`` says how many remain.
    """
    pid = table[py, px]
    if pid >= 0 and refs[pid] == 1:
        return pid
    left[i] -= 1
    new = block[left[i]]
    if pid < 0:
        for k in range(PATCH_CELLS):
            flags[new, k] = 0
            hits[new, k] = 0
            visits[new, k] = 0
            accx[new, k] = 0.0
            accy[new, k] = 0.0
    else:
        for k in range(PATCH_CELLS):
            flags[new, k] = flags[pid, k]
            hits[new, k] = hits[pid, k]
            visits[new, k] = visits[pid, k]
            accx[new, k] = accx[pid, k]
            accy[new, k] = accy[pid, k]
        copied[i, 0] += 1
        copied[i, copied[i, 0]] = pid
    # only this particle's table points to it, so no other thread reads this count
    refs[new] = 1
    table[py, px] = new
    return new


@njit(cache=True, inline="always")
def beam_patches(cells: int) -> int:
    """Most distinct patches a Bresenham line of ``cells`` cells can touch."""
    return 2 * (cells // (1 << PATCH_BITS) + 2) + 2


@njit(cache=True, error_model="numpy")
def _register_one(
    i: int,
    table: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    refs: NDArray[np.int32],
    block: NDArray[np.int32],
    left: NDArray[np.int64],
    copied: NDArray[np.int32],
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
) -> int:
    """OpenSLAM's ``registerScan`` into particle ``i``'s map, from beam ``start`` on.

    Each beam no longer than ``max_range`` marks the cells it passes through as visited; a beam
    no longer than ``usable`` also adds a hit (and the hit point) to its end cell, a longer one
    is cut at ``usable`` and its end cell is left alone.

    Returns:
        ``-1`` when done, or the beam to resume from: a beam starts only while the particle's
        block holds enough free ids for every patch it may touch, so no beam is ever half
        registered.
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
    # the patch of the last written cell: a ray stays 16 cells or more in one patch, so the
    # table and the reference count are read once per patch, not once per cell (the patch
    # stays this particle's own until the kernel returns)
    cpx = -1
    cpy = -1
    pid = -1
    for j in range(start, ranges.shape[0]):
        r = ranges[j]
        if not (r <= max_range) or r <= 0.0:
            continue
        cropped = r > usable
        d = usable if cropped else r
        dc = lc * ca[j] - ls * sa[j]
        ds = ls * ca[j] + lc * sa[j]
        hx = lx + d * dc
        hy = ly + d * ds
        x1 = math.floor((hx - ox) * inv)
        y1 = math.floor((hy - oy) * inv)
        dx = abs(x1 - x0)
        dy = -abs(y1 - y0)
        if left[i] < beam_patches(max(dx, -dy) + 1):
            return j
        # Bresenham from the laser cell to the end cell; every cell but the last is free
        sx = 1 if x0 < x1 else -1
        sy = 1 if y0 < y1 else -1
        err = dx + dy
        x = x0
        y = y0
        while True:
            last = x == x1 and y == y1
            if 0 <= x < nx and 0 <= y < ny and not (last and cropped):
                if (x >> PATCH_BITS) != cpx or (y >> PATCH_BITS) != cpy:
                    cpx = x >> PATCH_BITS
                    cpy = y >> PATCH_BITS
                    pid = _own_patch(
                        table, cpy, cpx, flags, hits, visits, accx, accy, refs, block, left,
                        copied, i,
                    )  # fmt: skip
                k = ((y & PATCH_MASK) << PATCH_BITS) | (x & PATCH_MASK)
                visits[pid, k] += 1
                if last:
                    hits[pid, k] += 1
                    accx[pid, k] += np.float32(hx - (ox + (x + 0.5) * delta))
                    accy[pid, k] += np.float32(hy - (oy + (y + 0.5) * delta))
                    flags[pid, k] = cell_flags(hits[pid, k], visits[pid, k])
                elif flags[pid, k]:
                    # a pass-through only lowers the hit ratio: a cell with no flag keeps none,
                    # so most cells of a ray skip the float comparisons
                    flags[pid, k] = cell_flags(hits[pid, k], visits[pid, k])
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


@njit(cache=True, error_model="numpy", parallel=True)
def register_particles(  # noqa: D417 (the scan arguments are those of `_register_one`)
    which: NDArray[np.int64],
    tables: NDArray[np.int32],
    flags: NDArray[np.uint8],
    hits: NDArray[np.int32],
    visits: NDArray[np.int32],
    accx: NDArray[np.float32],
    accy: NDArray[np.float32],
    refs: NDArray[np.int32],
    blocks: NDArray[np.int32],
    left: NDArray[np.int64],
    copied: NDArray[np.int32],
    starts: NDArray[np.int64],
    ox: float,
    oy: float,
    delta: float,
    poses: NDArray[np.float64],
    lo: NDArray[np.float64],
    ranges: NDArray[np.float64],
    ca: NDArray[np.float64],
    sa: NDArray[np.float64],
    usable: float,
    max_range: float,
) -> None:
    """Register one scan into the maps of particles ``which`` (in parallel, see module doc).

    Args:
        which: Particles to register, ``(M,)``; row ``q`` of ``blocks``, ``left``, ``copied``,
            ``starts`` and ``poses`` belongs to particle ``which[q]``.
        blocks: ``(M, Q)`` free patch ids reserved per particle; ``left[q]`` of them remain.
        copied: ``(M, Q + 1)``: count, then the shared patches copied (to release later).
        starts: Beam to start from per particle (``-1``: nothing to do); on return, where to
            resume (``-1``: done).
    """
    # one particle per iteration, each writing only its own table, patches and rows, so the
    # result does not depend on which thread runs which particle (the caller hands particles
    # out one at a time: `_kernels.one_particle_chunks`)
    for q in prange(which.shape[0]):
        if starts[q] < 0:
            continue
        starts[q] = _register_one(
            q, tables[which[q]], flags, hits, visits, accx, accy, refs, blocks[q], left, copied,
            ox, oy, delta, poses[q], lo, ranges, ca, sa, usable, max_range, starts[q],
        )  # fmt: skip


@njit(cache=True)
def release_copied(
    copied: NDArray[np.int32],
    refs: NDArray[np.int32],
    free: NDArray[np.int32],
    nfree: NDArray[np.int64],
) -> None:
    """Drop the references of the shared patches particles copied; free those left unused."""
    for q in range(copied.shape[0]):
        for c in range(1, copied[q, 0] + 1):
            pid = copied[q, c]
            refs[pid] -= 1
            if refs[pid] == 0:
                free[nfree[0]] = pid
                nfree[0] += 1
        copied[q, 0] = 0


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
