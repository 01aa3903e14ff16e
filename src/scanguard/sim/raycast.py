"""Ray casting with materials (numba) and the laser measurement model.

The kernel traces every beam against all segments and circles. Glass lets a beam through
(or echoes from the pane, or drops it); a mirror reflects it specularly, so the range is the
whole folded path length and the point appears *behind* the mirror, exactly like a real
phantom return. Randomness is passed in as uniforms drawn from a numpy Generator, so results are
bit-identical for a seed whatever numba's own RNG does.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanguard.scan import SensorInfo
from scanguard.sim.config import MaterialsConfig, SensorConfig

FloatArray = NDArray[np.float64]

_EPS = 1e-9


@njit(cache=True)
def _trace(
    ox: float,
    oy: float,
    cos_a: FloatArray,
    sin_a: FloatArray,
    segs: FloatArray,
    seg_mat: NDArray[np.int8],
    circles: FloatArray,
    circ_mat: NDArray[np.int8],
    uniforms: FloatArray,
    glass_reflect: float,
    glass_drop: float,
    mirror_spec: float,
    mirror_drop: float,
    max_bounces: int,
    max_path: float,
) -> FloatArray:  # pragma: no cover - compiled
    n = cos_a.shape[0]
    k = segs.shape[0]
    c = circles.shape[0]
    out = np.empty(n, dtype=np.float64)
    for i in range(n):
        px, py = ox, oy
        dx, dy = cos_a[i], sin_a[i]
        travelled = 0.0
        skip = -1  # primitive just left (segments 0..k-1, circles k..k+c-1)
        result = np.inf
        for bounce in range(max_bounces + 1):
            best = np.inf
            hit = -1
            nx = 0.0
            ny = 0.0
            for j in range(k):
                if j == skip:
                    continue
                x0 = segs[j, 0]
                y0 = segs[j, 1]
                ex = segs[j, 2] - x0
                ey = segs[j, 3] - y0
                denom = dx * ey - dy * ex
                if denom == 0.0:
                    continue
                wx = x0 - px
                wy = y0 - py
                t = (wx * ey - wy * ex) / denom
                if t <= _EPS or t >= best:
                    continue
                u = (wx * dy - wy * dx) / denom
                if u < 0.0 or u > 1.0:
                    continue
                best = t
                hit = j
            for j in range(c):
                if j + k == skip:
                    continue
                cx = circles[j, 0] - px
                cy = circles[j, 1] - py
                r = circles[j, 2]
                b = cx * dx + cy * dy
                if b <= 0.0:
                    continue
                disc = b * b - (cx * cx + cy * cy - r * r)
                if disc < 0.0:
                    continue
                t = b - math.sqrt(disc)
                if t <= _EPS or t >= best:
                    continue
                best = t
                hit = j + k
            if hit < 0 or travelled + best > max_path:
                result = np.inf
                break
            mat = seg_mat[hit] if hit < k else circ_mat[hit - k]
            if mat == 0:
                result = travelled + best
                break
            u = uniforms[i, bounce]
            if mat == 1:  # glass
                if u < glass_reflect:
                    result = travelled + best
                    break
                if u < glass_reflect + glass_drop:
                    result = np.inf
                    break
            else:  # mirror
                if u >= mirror_spec + mirror_drop:
                    result = travelled + best
                    break
                if u >= mirror_spec:
                    result = np.inf
                    break
                if hit < k:
                    ex = segs[hit, 2] - segs[hit, 0]
                    ey = segs[hit, 3] - segs[hit, 1]
                    norm = math.sqrt(ex * ex + ey * ey)
                    nx = -ey / norm
                    ny = ex / norm
                else:
                    hx = px + best * dx - circles[hit - k, 0]
                    hy = py + best * dy - circles[hit - k, 1]
                    norm = math.sqrt(hx * hx + hy * hy)
                    nx = hx / norm
                    ny = hy / norm
                dn = dx * nx + dy * ny
                px = px + best * dx
                py = py + best * dy
                dx = dx - 2.0 * dn * nx
                dy = dy - 2.0 * dn * ny
                travelled += best
                skip = hit
                continue
            # glass pass-through: same direction, from the pane onwards
            px = px + best * dx
            py = py + best * dy
            travelled += best
            skip = hit
        out[i] = result
    return out


@njit(cache=True)
def _primary(
    ox: float,
    oy: float,
    theta0: float,
    inc: float,
    cos_a: FloatArray,
    sin_a: FloatArray,
    segs: FloatArray,
    circles: FloatArray,
) -> tuple[FloatArray, NDArray[np.int64]]:  # pragma: no cover - compiled
    """Nearest first hit per beam, visiting only the beams each primitive's angular span covers.

    Beam ``i`` points at ``theta0 + i * inc``; the cost is the sum of the primitives' spans
    instead of beams x primitives.
    """
    n = cos_a.shape[0]
    k = segs.shape[0]
    two_pi = 2.0 * math.pi
    best = np.full(n, np.inf)
    hit = np.full(n, -1, dtype=np.int64)
    for j in range(k + circles.shape[0]):
        if j < k:
            x0 = segs[j, 0]
            y0 = segs[j, 1]
            ex = segs[j, 2] - x0
            ey = segs[j, 3] - y0
            r0 = (math.atan2(y0 - oy, x0 - ox) - theta0) % two_pi
            r1 = (math.atan2(segs[j, 3] - oy, segs[j, 2] - ox) - theta0) % two_pi
            span = (r1 - r0) % two_pi
            start = r0
            if span > math.pi:
                start = r1
                span = two_pi - span
        else:
            cx = circles[j - k, 0] - ox
            cy = circles[j - k, 1] - oy
            rad = circles[j - k, 2]
            d = math.sqrt(cx * cx + cy * cy)
            if d <= rad:
                continue
            half = math.asin(rad / d)
            start = (math.atan2(cy, cx) - half - theta0) % two_pi
            span = 2.0 * half
        # one beam of margin on each side; the exact test below decides
        lo = math.floor(start / inc) - 1
        hi = math.ceil((start + span) / inc) + 1
        nfull = math.ceil(two_pi / inc - 1e-9)
        for ii in range(lo, hi + 1):
            i = ii % nfull
            if i >= n:
                continue
            dx = cos_a[i]
            dy = sin_a[i]
            if j < k:
                denom = dx * ey - dy * ex
                if denom == 0.0:
                    continue
                wx = x0 - ox
                wy = y0 - oy
                t = (wx * ey - wy * ex) / denom
                if t <= _EPS or t >= best[i]:
                    continue
                u = (wx * dy - wy * dx) / denom
                if u < 0.0 or u > 1.0:
                    continue
            else:
                b = cx * dx + cy * dy
                if b <= 0.0:
                    continue
                disc = b * b - (cx * cx + cy * cy - rad * rad)
                if disc < 0.0:
                    continue
                t = b - math.sqrt(disc)
                if t <= _EPS or t >= best[i]:
                    continue
            best[i] = t
            hit[i] = j
    return best, hit


def cast_rays(
    origin: FloatArray,
    angles: FloatArray,
    segments: FloatArray,
    segment_material: NDArray[np.int8],
    circles: FloatArray,
    circle_material: NDArray[np.int8],
    materials: MaterialsConfig | None = None,
    rng: np.random.Generator | None = None,
    max_range: float = np.inf,
) -> FloatArray:
    """True (noise-free) ranges of rays from ``origin`` at world ``angles``.

    Args:
        origin: Ray origin ``(x, y)`` in the world.
        angles: World-frame ray directions (rad), shape ``(n,)``.
        segments: Segments ``(K, 4)``.
        segment_material: Material codes ``(K,)``.
        circles: Circles ``(C, 3)`` ``(x, y, r)``.
        circle_material: Material codes ``(C,)``.
        materials: Glass/mirror behaviour (defaults when None).
        rng: Draws for glass/mirror outcomes (only needed when such surfaces exist).
        max_range: Folded paths longer than this are reported as inf.

    Returns:
        Ranges ``(n,)`` (inf when nothing is hit, a beam drops out, or the path is too long).
    """
    m = materials or MaterialsConfig()
    angles = np.asarray(angles, dtype=np.float64)
    segs = np.ascontiguousarray(segments, dtype=np.float64).reshape(-1, 4)
    smat = np.ascontiguousarray(segment_material, dtype=np.int8)
    circ = np.ascontiguousarray(circles, dtype=np.float64).reshape(-1, 3)
    cmat = np.ascontiguousarray(circle_material, dtype=np.int8)
    cos_a, sin_a = np.cos(angles), np.sin(angles)
    n = angles.size
    special = bool(np.any(smat != 0) or np.any(cmat != 0))
    if special:
        gen = rng if rng is not None else np.random.default_rng(0)
        uniforms = gen.random((n, m.max_bounces + 1))
    else:
        uniforms = np.zeros((n, m.max_bounces + 1))
    inc = float(angles[1] - angles[0]) if n > 1 else 1.0
    evenly = n > 1 and inc > 0 and float(np.max(np.abs(np.diff(angles) - inc))) <= 1e-9
    if evenly:
        best, hit = _primary(
            float(origin[0]), float(origin[1]), float(angles[0]), inc, cos_a, sin_a, segs, circ
        )
        mats = np.concatenate([smat, cmat])
        ranges = np.where(best <= max_range, best, np.inf)
        hit_mat = np.where(hit >= 0, mats[np.maximum(hit, 0)], 0) if mats.size else hit * 0
        todo = np.nonzero(hit_mat != 0)[0]
    else:
        ranges = np.full(n, np.inf)
        todo = np.arange(n)
    if todo.size:
        # beams that met glass or a mirror (or irregular beam layouts): full multi-bounce trace
        ranges[todo] = _trace(
            float(origin[0]),
            float(origin[1]),
            np.ascontiguousarray(cos_a[todo]),
            np.ascontiguousarray(sin_a[todo]),
            segs,
            smat,
            circ,
            cmat,
            np.ascontiguousarray(uniforms[todo]),
            m.glass.reflect_prob,
            m.glass.dropout_prob,
            m.mirror.specular_prob,
            m.mirror.dropout_prob,
            m.max_bounces,
            float(max_range),
        )
    return np.asarray(ranges, dtype=np.float64)


def measure(
    true_ranges: FloatArray,
    sensor: SensorConfig,
    info: SensorInfo,
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    """Apply the laser's measurement model to true ranges.

    Gaussian noise with std ``noise_std + noise_rel * r``, random dropouts, optional mixed
    pixels on depth edges, and — like the RPLidar/urg drivers — inf for anything without a
    valid return (beyond ``range_max``, below ``range_min``, dropped).

    Args:
        true_ranges: Exact ranges ``(n,)`` (inf = no hit).
        sensor: Sensor configuration (noise parameters).
        info: Resolved sensor geometry and limits.
        rng: Noise source.

    Returns:
        Measured ranges as float32.
    """
    r = np.array(true_ranges, dtype=np.float64)
    n = r.size
    sd, rel = sensor.sigma
    # always draw, so the random stream does not depend on which beams hit something
    gauss = rng.standard_normal(n)
    drop = rng.random(n)
    mix = rng.random(n)
    mix_t = rng.random(n)
    finite = np.isfinite(r)
    if sensor.mixed_pixel_prob > 0:
        nxt = np.roll(r, -1)
        edge = finite & np.isfinite(nxt) & (np.abs(nxt - r) > 0.3)
        sel = edge & (mix < sensor.mixed_pixel_prob)
        r = np.where(sel, r + mix_t * (nxt - r), r)
    if sd > 0 or rel > 0:
        r = np.where(finite, r + gauss * (sd + rel * np.where(finite, r, 0.0)), r)
    r = np.where(drop < sensor.dropout_prob, np.inf, r)
    with np.errstate(invalid="ignore"):
        r = np.where((r > info.range_max) | (r < info.range_min), np.inf, r)
    return r.astype(np.float32)
