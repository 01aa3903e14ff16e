"""The pure-numpy reference renderer: the definition the numba kernels must reproduce.

`render_pairs_numpy` has the contract of `scanguard.detect.render.render_pairs` and gives
byte-identical images; it is not used in production (the kernels are 5-20x faster), the tests
compare the two. It shares the input checks, marker offsets and colouring of
`scanguard.detect.render` (imported here although private there: they are one renderer's
parts, split only to keep the production module short).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.detect._render_kernels import MIN_HALF_SIDE
from scanguard.detect.render import (
    PointsLike,
    RenderStyle,
    _as_array,
    _check_poses,
    _colourise,
    _disc_offsets,
)

# Pairs prepared per chunk: small enough for the per-point arrays to stay in the CPU caches
# (measured fastest between 8 and 16 with 1440-beam scans).
_CHUNK = 16


class Prepared:
    """Points of a chunk of pairs as pixel indices, plus each pair's extent.

    All previous scans come first, then all current scans (previous points need no
    transform). Coordinates live in two contiguous arrays (x, y) and every step is one
    vectorised pass over all points of the chunk; the number of numpy calls, not the
    arithmetic, dominates the cost of a single pair, so the code keeps them few.

    Attributes:
        flat: Index of every drawn point's pixel in the padded ``(B, full, full)`` canvas;
            the first ``n_previous`` belong to previous scans, the rest to current scans.
        n_previous: Number of previous-scan entries at the start of ``flat``.
        extents: ``(B, 3)`` ``(x_min, y_min, side)`` per pair.
    """

    def __init__(
        self,
        previous_list: Sequence[PointsLike | ArrayLike],
        current_list: Sequence[PointsLike | ArrayLike],
        poses: NDArray[np.float64],
        style: RenderStyle,
        offset: int = 0,
    ) -> None:
        n = len(previous_list)
        arrays = [_as_array(a, f"pair {offset + i} previous") for i, a in enumerate(previous_list)]
        arrays += [_as_array(a, f"pair {offset + i} current") for i, a in enumerate(current_list)]
        cnt = np.array([len(a) for a in arrays], dtype=np.intp)
        n_prev = int(cnt[:n].sum())
        # (2, K): one row per coordinate, so each step is one call over all points.
        xy = np.ascontiguousarray(np.concatenate(arrays).T, dtype=np.float64)
        _move_current(xy, cnt, poses, n, n_prev)
        bounds = _scan_bounds(xy, cnt)
        if not np.isfinite(bounds[:, cnt > 0]).all():
            # Some point is NaN or inf (min/max propagate both): drop those points.
            seg = np.repeat(np.arange(2 * n), cnt)
            finite = np.isfinite(xy).all(axis=0)
            seg, xy = seg[finite], xy[:, finite]
            cnt = np.bincount(seg, minlength=2 * n)
            n_prev = int(cnt[:n].sum())
            bounds = _scan_bounds(xy, cnt)
        self.extents = ext = _extents(bounds, style)
        self.flat, self.n_previous = _pixel_indices(xy, cnt, ext, style, n, n_prev)


def _move_current(
    xy: NDArray[np.float64], cnt: NDArray[np.intp], poses: NDArray[np.float64], n: int, n_prev: int
) -> None:
    """Move the current scans' points (columns from ``n_prev`` on) by their poses, in place."""
    total = xy.shape[1]
    if total > n_prev:
        cur = xy[:, n_prev:]
        with np.errstate(invalid="ignore"):  # NaN points are dropped below
            if n == 1:
                c, s_ = np.cos(poses[0, 2]), np.sin(poses[0, 2])
                cur[...] = np.array([[c, -s_], [s_, c]]) @ cur
                cur += poses[0, :2, None]
            else:
                # Per-point values by np.repeat of per-scan values: much faster than
                # gathering with a per-point pair index.
                rep = np.repeat(
                    np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2]), poses[:, 0], poses[:, 1]]),
                    cnt[n:],
                    axis=1,
                )
                c, s_ = rep[0], rep[1]
                new_x = c * cur[0] - s_ * cur[1] + rep[2]
                cur[1] *= c
                cur[1] += s_ * cur[0] + rep[3]
                cur[0] = new_x


def _pixel_indices(
    xy: NDArray[np.float64],
    cnt: NDArray[np.intp],
    ext: NDArray[np.float64],
    style: RenderStyle,
    n: int,
    n_prev: int,
) -> tuple[NDArray[np.intp], int]:
    """Flat canvas index of every drawn point and the number of previous-scan entries.

    ``xy`` (the finite points, previous scans first) is scaled in place.
    """
    size = style.size
    pad = int(np.floor(style.point_radius))
    full = size + 2 * pad
    # col = (x - x0) * k + 0.5 and row = (y0 + side - y) * k + 0.5 with k = size / side,
    # floored: the nearest pixel centre (centres at x0 + j * side / size). Rounding, not
    # flooring, matches where matplotlib's Agg backend snaps markers and puts the metric
    # style's sensor origin exactly on the centre of pixel (size/2, size/2).
    k = size / ext[:, 2]
    shift = np.stack([0.5 - ext[:, 0] * k, 0.5 + (ext[:, 1] + ext[:, 2]) * k])
    base: Any
    if n == 1:
        xy *= np.array([[k[0]], [-k[0]]])
        xy += shift
        base = pad * full + pad
    else:
        per_scan = np.concatenate([np.stack([k, -k, *shift]), np.stack([k, -k, *shift])], axis=1)
        rep = np.repeat(per_scan, cnt, axis=1)
        xy *= rep[:2]
        xy += rep[2:]
        pair_base = np.arange(n) * (full * full) + (pad * full + pad)
        base = np.repeat(np.concatenate([pair_base, pair_base]), cnt)
    np.floor(xy, out=xy)
    if style.kind == "metric":
        inside: NDArray[np.bool_] = np.asarray(((xy >= 0) & (xy < size)).all(axis=0))
        if not inside.all():
            n_prev = int(inside[:n_prev].sum())
            xy = xy[:, inside]
            if n > 1:
                base = base[inside]
    elif style.margin * size / (2.0 + 2.0 * style.margin) <= 0.5 + 1e-9:
        # An auto-fitted extent with a margin of at least half a pixel keeps every point
        # inside; only a thinner margin can push a border point just past the last pixel.
        np.minimum(xy, size - 1, out=xy)
    xy[1] *= full
    xy[1] += xy[0]
    return xy[1].astype(np.intp) + base, n_prev


def _scan_bounds(xy: NDArray[np.float64], cnt: NDArray[np.intp]) -> NDArray[np.float64]:
    """``(4, S)`` x-min, y-min, x-max, y-max of each of ``S`` scans stored in runs of ``cnt``.

    Empty scans get NaN; a NaN or inf point shows up as a non-finite bound.
    """
    has = cnt > 0
    if has.all():
        starts = np.cumsum(cnt) - cnt
        return np.concatenate(
            [np.minimum.reduceat(xy, starts, axis=1), np.maximum.reduceat(xy, starts, axis=1)]
        )
    out = np.full((4, len(cnt)), np.nan)
    if has.any():
        starts = (np.cumsum(cnt) - cnt)[has]
        out[:2, has] = np.minimum.reduceat(xy, starts, axis=1)
        out[2:, has] = np.maximum.reduceat(xy, starts, axis=1)
    return out


def _extents(bounds: NDArray[np.float64], style: RenderStyle) -> NDArray[np.float64]:
    """``(n, 3)`` lower-left corner and side (m) of each pair's square drawn area.

    ``bounds`` are the per-scan bounds of ``2n`` scans: all previous, then all current.
    """
    n = bounds.shape[1] // 2
    if style.kind == "metric":
        side = style.size * style.resolution
        return np.tile([-side / 2.0, -side / 2.0, side], (n, 1))
    lo = np.fmin(bounds[:2, :n], bounds[:2, n:])  # fmin/fmax skip the NaN of empty scans
    hi = np.fmax(bounds[2:, :n], bounds[2:, n:])
    centre = (lo + hi) / 2.0
    half = (hi - lo).max(axis=0) / 2.0
    # No points: a fixed extent around the origin. All points coincide: any fixed extent
    # will do, but it must not collapse to zero.
    tiny = ~(half >= 1e-6)  # also true for NaN (no points)
    if tiny.any():
        centre[:, np.isnan(half)] = 0.0
        half[tiny] = MIN_HALF_SIDE
    half *= 1.0 + style.margin
    out = np.empty((n, 3))
    out[:, :2] = (centre - half).T
    out[:, 2] = 2.0 * half
    return out


def render_pairs_numpy(
    previous_list: Sequence[PointsLike | ArrayLike],
    current_list: Sequence[PointsLike | ArrayLike],
    poses: ArrayLike,
    style: RenderStyle,
) -> NDArray[np.uint8]:
    """Pure-numpy reference renderer: the definition the numba kernel must reproduce.

    Same contract as `render_pairs`. Not used in production (the kernel is 5-20x faster);
    tests compare the two byte for byte.
    """
    n = len(previous_list)
    pose_arr = _check_poses(poses, n, len(current_list))
    if style.kind == "multiscale":
        return np.concatenate(
            [render_pairs_numpy(previous_list, current_list, pose_arr, v) for v in style.views()],
            axis=-1,
        )
    size = style.size
    offsets = [o for o in _disc_offsets(style.point_radius) if o != (0, 0)]
    pad = int(np.floor(style.point_radius))
    full = size + 2 * pad
    out = np.empty((n, size, size, style.channels), dtype=np.uint8)
    code = np.empty((size, size), dtype=np.uint8)
    for start in range(0, n, _CHUNK):
        stop = min(start + _CHUNK, n)
        prep = Prepared(
            previous_list[start:stop], current_list[start:stop], pose_arr[start:stop], style, start
        )
        # 2-bit code per pixel: bit 0 = previous scan, bit 1 = current scan. The canvas is
        # padded by the marker radius so that markers at the border need no clipping.
        canvas = np.zeros((stop - start, full, full), dtype=np.uint8)
        lin = canvas.reshape(-1)
        lin[prep.flat[: prep.n_previous]] = 1
        # Duplicate indices all write the same value, so the buffered |= is exact.
        lin[prep.flat[prep.n_previous :]] |= 2
        # Markers and colours image by image: each image's buffers stay in the CPU caches.
        for j in range(stop - start):
            img = canvas[j]
            code[...] = img[pad : pad + size, pad : pad + size]
            for dy, dx in offsets:
                code |= img[pad + dy : pad + dy + size, pad + dx : pad + dx + size]
            _colourise(code, style, out[start + j])
    return out
