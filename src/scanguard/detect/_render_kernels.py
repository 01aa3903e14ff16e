"""The numba kernels of `scanguard.detect.render` (compiled; the Python API lives there).

One pass per pair: transform and bound the points, fill the image with the background, then
stamp each point's marker straight into the uint8 image. Only touched pixels are written after
the fill, so the cost is ~points x marker pixels instead of several whole-image passes. The
arithmetic mirrors `scanguard.detect.render_reference.render_pairs_numpy` operation for
operation (same association, no fastmath, so no FMA contraction): both give the same pixel
indices bit for bit.

Unusual constructs, on purpose:

* ``x, y = (cs * x - sn * y) + tx, y * cs + (sn * x + ty)`` spells out the association of the
  numpy reference's in-place updates; rewriting it "more naturally" changes the last bit.
* ``flat = out.reshape(-1)`` and writes through flat indices: numba creates no per-pixel view
  objects that way.
* Module-level constants (``MODE_*``, ``MIN_HALF_SIDE``) are frozen into the compiled code
  as literals; ``cache=True`` keeps the machine code between runs (recompiled when this file
  changes).
* ``# fmt: skip`` keeps long positional kernel calls on few lines (the formatter would put
  every argument on its own line).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

# Half-side (m) used when all points coincide, so that the extent never collapses to zero.
MIN_HALF_SIDE = 0.5

# Kernel drawing modes: how a marker pixel changes the image.
MODE_MIX = 0  # paper, overlap="mix": red | blue -> magenta
MODE_CURRENT = 1  # paper, overlap="current": blue over red
MODE_OCC = 2  # two channels (previous, current), 255 = hit


@njit(cache=True, nogil=True)
def pair_extent(
    pts: Any,
    p0: int,
    p1: int,
    c1: int,
    cs: float,
    sn: float,
    tx: float,
    ty: float,
    metric: bool,
    size: int,
    margin: float,
    resolution: float,
    ext: Any,
) -> None:  # pragma: no cover - compiled
    """Write ``(x_min, y_min, side)`` of one pair into ``ext``.

    The kernel form of `scanguard.detect.render_reference`'s extents.
    """
    if metric:
        side = size * resolution
        ext[0] = -side / 2.0
        ext[1] = -side / 2.0
        ext[2] = side
        return
    lox = np.inf
    loy = np.inf
    hix = -np.inf
    hiy = -np.inf
    for i in range(p0, c1):
        x = np.float64(pts[i, 0])
        y = np.float64(pts[i, 1])
        if i >= p1:
            x, y = (cs * x - sn * y) + tx, y * cs + (sn * x + ty)
        if np.isfinite(x) and np.isfinite(y):
            lox = min(lox, x)
            hix = max(hix, x)
            loy = min(loy, y)
            hiy = max(hiy, y)
    if lox > hix:  # no finite point: a fixed extent around the origin
        cx = 0.0
        cy = 0.0
        half = MIN_HALF_SIDE
    else:
        cx = (lox + hix) / 2.0
        cy = (loy + hiy) / 2.0
        half = max(hix - lox, hiy - loy) / 2.0
        if not half >= 1e-6:
            half = MIN_HALF_SIDE
    half *= 1.0 + margin
    ext[0] = cx - half
    ext[1] = cy - half
    ext[2] = 2.0 * half


@njit(cache=True, nogil=True)
def extents_kernel(
    pts: Any,
    starts: Any,
    cos: Any,
    sin: Any,
    poses: Any,
    metric: bool,
    size: int,
    margin: float,
    resolution: float,
    ext: Any,
) -> None:  # pragma: no cover - compiled
    for b in range(ext.shape[0]):
        pair_extent(
            pts, starts[2 * b], starts[2 * b + 1], starts[2 * b + 2], cos[b], sin[b],
            poses[b, 0], poses[b, 1], metric, size, margin, resolution, ext[b],
        )  # fmt: skip


@njit(cache=True, nogil=True)
def render_kernel(
    pts: Any,
    starts: Any,
    cos: Any,
    sin: Any,
    poses: Any,
    mode: int,
    metric: bool,
    clip: bool,
    margin: float,
    resolution: float,
    dys: Any,
    dxs: Any,
    out: Any,
    ext: Any,
) -> None:  # pragma: no cover - compiled
    size = out.shape[1]
    nch = out.shape[3]
    npix = size * size * nch
    fsize = np.float64(size)
    background = np.uint8(0) if mode == MODE_OCC else np.uint8(255)
    flat = out.reshape(-1)  # writes through flat indices: no per-pixel view objects
    n_off = dys.shape[0]
    deltas = (dys * size + dxs) * nch
    reach = 0
    for o in range(n_off):
        reach = max(reach, abs(dys[o]), abs(dxs[o]))
    for b in range(out.shape[0]):
        p0, p1, c1 = starts[2 * b], starts[2 * b + 1], starts[2 * b + 2]
        cs, sn, tx, ty = cos[b], sin[b], poses[b, 0], poses[b, 1]
        pair_extent(pts, p0, p1, c1, cs, sn, tx, ty, metric, size, margin, resolution, ext[b])
        k = size / ext[b, 2]
        sx = 0.5 - ext[b, 0] * k
        sy = 0.5 + (ext[b, 1] + ext[b, 2]) * k
        base = b * npix
        flat[base : base + npix] = background
        last = -1
        last_current = False
        for i in range(p0, c1):
            x = np.float64(pts[i, 0])
            y = np.float64(pts[i, 1])
            current = i >= p1
            if current:
                x, y = (cs * x - sn * y) + tx, y * cs + (sn * x + ty)
            if not (np.isfinite(x) and np.isfinite(y)):
                continue
            col = np.floor(x * k + sx)
            row = np.floor(y * -k + sy)
            if clip:
                col = min(col, fsize - 1.0)
                row = min(row, fsize - 1.0)
            # Metric crops to the image; an auto-fitted extent keeps every point inside, so
            # there this only guards memory.
            if not (col >= 0.0 and col < fsize and row >= 0.0 and row < fsize):
                continue
            r0 = int(row)
            q0 = int(col)
            j0 = base + (r0 * size + q0) * nch
            if j0 == last and current == last_current:
                # Consecutive beams often land on the same pixel; a marker drawn twice by the
                # same scan changes nothing.
                continue
            last = j0
            last_current = current
            if r0 >= reach and r0 < size - reach and q0 >= reach and q0 < size - reach:
                # Whole marker inside: precomputed flat offsets, no per-pixel bounds checks.
                for o in range(n_off):
                    stamp(flat, j0 + deltas[o], mode, current)
            else:
                for o in range(n_off):
                    r = r0 + dys[o]
                    q = q0 + dxs[o]
                    if r >= 0 and r < size and q >= 0 and q < size:
                        stamp(flat, j0 + deltas[o], mode, current)


@njit(cache=True, nogil=True)
def stamp(flat: Any, j: int, mode: int, current: bool) -> None:  # pragma: no cover - compiled
    """Mark pixel ``flat[j:j + C]`` as hit by the previous or the current scan."""
    if mode == MODE_OCC:
        flat[j + 1 if current else j] = 255
    elif not current:  # previous scans are drawn first: the pixel is white or red
        flat[j + 1] = 0
        flat[j + 2] = 0
    else:
        # "current": blue over anything. "mix": white becomes blue, red becomes magenta;
        # G is 255 only on background, so R & ~G keeps R exactly on red (branch-free).
        flat[j] = 0 if mode == MODE_CURRENT else flat[j] & ~flat[j + 1]
        flat[j + 1] = 0
        flat[j + 2] = 255
