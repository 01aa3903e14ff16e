"""Numba ICP loops (point-to-point, point-to-line) and the final-alignment statistics.

Status codes returned by the loops: 0 = ran, 1 = too few pairs, 2 = estimate diverged.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from scanguard.matching._grid import (
    COVER_MAX_TARGET_RATIO,
    Cover,
    Grid,
    block_normals,
    build_cover,
    build_grid,
    cached_normal,
    choose_cell_size,
    cover_nearest,
    cover_radius,
    grid_nearest,
    kth_smallest,
    median,
    no_cover,
    pending_block_normals,
    point_normal,
)

# (x, y, theta, iterations, converged, status, mean distance, median distance, hessian,
# eigenvalues, n_inliers) of each match of `run_match`
MatchTuple = tuple[
    float, float, float, int, bool, int, float, float, NDArray[np.float64], NDArray[np.float64],
    int,
]  # fmt: skip
STATUS_OK = 0
STATUS_FEW_PAIRS = 1
STATUS_DIVERGED = 2


# Every kernel is ``nogil=True``: it touches no Python object, and releasing the GIL lets the
# back-end instances of a run update side by side on threads (`scanguard.slam.loop.RunLoop`).
@njit(cache=True, error_model="numpy", nogil=True)
def all_finite(a: NDArray[np.float64]) -> bool:
    """Whether every entry of ``a`` (2-D, C-contiguous) is finite; one pass, no temporaries.

    Tests the exponent bits (all ones: inf or NaN) with an OR over the whole array, a
    branch-free loop the compiler vectorises (~1 us for 1440 points, ~6 us per-element).
    """
    bits = a.reshape(-1).view(np.uint64)
    exp = np.uint64(0x7FF0000000000000)
    bad = np.uint64(0)
    for i in range(bits.shape[0]):
        bad |= np.uint64(1) if (bits[i] & exp) == exp else np.uint64(0)
    return bad == 0


@njit(cache=True, error_model="numpy", nogil=True)
def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, error_model="numpy", nogil=True)
def _p2p_step(
    m: int,
    spx: float,
    spy: float,
    sqx: float,
    sqy: float,
    sxx: float,
    sxy: float,
    syx: float,
    syy: float,
) -> tuple[float, float, float]:
    """Point-to-point update ``(dtx, dty, dth)`` from the pair sums (centred Procrustes).

    The rotation is the SVD solution ``R = U V^T`` (with the reflection fix) of the 2x2
    cross-covariance; in 2D it has the closed form ``theta = atan2(sum(p x q), sum(p . q))``
    over centred pairs (the numpy reference in ``scanguard.matching.reference`` uses the SVD
    and agrees to 1e-9); ``t = mu_Q - R mu_P``.
    """
    mpx = spx / m
    mpy = spy / m
    mqx = sqx / m
    mqy = sqy / m
    cxx = sxx / m - mpx * mqx
    cxy = sxy / m - mpx * mqy
    cyx = syx / m - mpy * mqx
    cyy = syy / m - mpy * mqy
    dth = math.atan2(cxy - cyx, cxx + cyy)
    cd = math.cos(dth)
    sd = math.sin(dth)
    dtx = mqx - (cd * mpx - sd * mpy)
    dty = mqy - (sd * mpx + cd * mpy)
    return dtx, dty, dth


@njit(cache=True, error_model="numpy", nogil=True)
def _pl_step(
    m: int,
    d2s: NDArray[np.float64],
    res: NDArray[np.float64],
    jac: NDArray[np.float64],
    trim_fraction: float,
    huber: float,
) -> tuple[float, float, float]:
    """Point-to-line Gauss-Newton update ``(dtx, dty, dth)``: closest pairs, Huber weights."""
    keep = m
    if trim_fraction < 1.0:
        keep = max(3, math.ceil(trim_fraction * m))
    cut = np.inf
    if keep < m:
        cut = kth_smallest(d2s[:m].copy(), keep - 1)
    h = np.zeros((3, 3))
    g = np.zeros(3)
    for k in range(m):
        if d2s[k] > cut:
            continue
        r = res[k]
        w = 1.0
        if huber > 0.0 and abs(r) > huber:
            w = huber / abs(r)
        for a in range(3):
            g[a] += w * jac[k, a] * r
            for b in range(3):
                h[a, b] += w * jac[k, a] * jac[k, b]
    step = _solve3(h, g)
    dtx = step[0]
    dty = step[1]
    dth = step[2]
    return dtx, dty, dth


@njit(cache=True, error_model="numpy", nogil=True)
def _apply_step(
    x: float,
    y: float,
    th: float,
    dtx: float,
    dty: float,
    dth: float,
    tol_t: float,
    tol_r: float,
    paper_rule: bool,
) -> tuple[float, float, float, int, bool]:
    """Compose the update onto the pose; report divergence and the stop rule.

    The paper's rule stops on the update's translation alone; the default also needs the
    rotation increment below ``tol_r``.
    """
    cd = math.cos(dth)
    sd = math.sin(dth)
    xn = cd * x - sd * y + dtx
    yn = sd * x + cd * y + dty
    thn = _wrap(th + dth)
    if not (math.isfinite(xn) and math.isfinite(yn) and math.isfinite(thn)):
        return xn, yn, thn, STATUS_DIVERGED, False
    done = math.hypot(dtx, dty) < tol_t and (paper_rule or abs(dth) < tol_r)
    return xn, yn, thn, STATUS_OK, done


@njit(cache=True, error_model="numpy", nogil=True)
def _cover_cell(qx: float, qy: float, x0: float, y0: float, inv: float, nx: int, ny: int) -> int:
    """Cover cell of a query (same arithmetic as `cover_nearest`), -1 outside the cover."""
    fx = (qx - x0) * inv
    fy = (qy - y0) * inv
    if not (fx >= 0.0 and fy >= 0.0):
        return -1
    ix = int(fx)
    iy = int(fy)
    if ix >= nx or iy >= ny:
        return -1
    return iy * nx + ix


@njit(cache=True, error_model="numpy", nogil=True)
def nn_chunk(
    src: NDArray[np.float64],
    x: float,
    y: float,
    th: float,
    grid: Grid,
    cover: Cover,
    max_d2: float,
    nn: NDArray[np.int64],
    d2s: NDArray[np.float64],
    lo: int,
    hi: int,
) -> None:
    """Exact nearest neighbours of source points ``lo:hi`` at pose ``(x, y, th)``.

    Consecutive points of a scan mostly fall into the same cover cell, so runs of up to four
    of them share one scan of its list (four independent minima per loaded point: ~2x
    cheaper per query than one scan each). Queries the cover does not certify go to
    `grid_nearest`, with the point's last neighbour (``nn``) and the previous point's as
    hints. Writes ``nn`` (index into the sorted target points, -1: none within ``max_d2``)
    and ``d2s`` (squared distance) in place; they do not depend on the hints.
    """
    start, spts, x0, y0, cell, nx, ny = grid
    cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2 = cover
    c = math.cos(th)
    s = math.sin(th)
    lane_x = np.empty(4)
    lane_y = np.empty(4)
    lane_j = np.empty(4, dtype=np.int64)
    lane_d = np.empty(4)
    last = -1
    i = lo
    while i < hi:
        q0x = c * src[i, 0] - s * src[i, 1] + x
        q0y = s * src[i, 0] + c * src[i, 1] + y
        cc = _cover_cell(q0x, q0y, cx0, cy0, cinv, cnx, cny)
        # the run: the following points while they share the cell (unused lanes repeat
        # the last query; their results are ignored)
        run = 1
        q1x = q0x
        q1y = q0y
        if cc >= 0 and i + 1 < hi:
            tx = c * src[i + 1, 0] - s * src[i + 1, 1] + x
            ty = s * src[i + 1, 0] + c * src[i + 1, 1] + y
            if _cover_cell(tx, ty, cx0, cy0, cinv, cnx, cny) == cc:
                q1x = tx
                q1y = ty
                run = 2
        q2x = q1x
        q2y = q1y
        if run == 2 and i + 2 < hi:
            tx = c * src[i + 2, 0] - s * src[i + 2, 1] + x
            ty = s * src[i + 2, 0] + c * src[i + 2, 1] + y
            if _cover_cell(tx, ty, cx0, cy0, cinv, cnx, cny) == cc:
                q2x = tx
                q2y = ty
                run = 3
        q3x = q2x
        q3y = q2y
        if run == 3 and i + 3 < hi:
            tx = c * src[i + 3, 0] - s * src[i + 3, 1] + x
            ty = s * src[i + 3, 0] + c * src[i + 3, 1] + y
            if _cover_cell(tx, ty, cx0, cy0, cinv, cnx, cny) == cc:
                q3x = tx
                q3y = ty
                run = 4
        lane_x[0] = q0x
        lane_y[0] = q0y
        if run == 1:
            j, d2 = cover_nearest(q0x, q0y, cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2)
            lane_j[0] = j
            lane_d[0] = d2
        else:
            lane_x[1] = q1x
            lane_y[1] = q1y
            lane_x[2] = q2x
            lane_y[2] = q2y
            lane_x[3] = q3x
            lane_y[3] = q3y
            b0 = np.inf
            b1 = np.inf
            b2 = np.inf
            b3 = np.inf
            k0 = -1
            k1 = -1
            k2 = -1
            k3 = -1
            for k in range(cs[cc], cs[cc + 1]):
                ex = cx[k]
                ey = cy[k]
                dx = ex - q0x
                dy = ey - q0y
                d2 = dx * dx + dy * dy
                if d2 < b0:
                    b0 = d2
                    k0 = k
                dx = ex - q1x
                dy = ey - q1y
                d2 = dx * dx + dy * dy
                if d2 < b1:
                    b1 = d2
                    k1 = k
                dx = ex - q2x
                dy = ey - q2y
                d2 = dx * dx + dy * dy
                if d2 < b2:
                    b2 = d2
                    k2 = k
                dx = ex - q3x
                dy = ey - q3y
                d2 = dx * dx + dy * dy
                if d2 < b3:
                    b3 = d2
                    k3 = k
            # as `cover_nearest`: certified (index, d2), else (-2, candidate index or -1)
            lane_j[0] = -2 if k0 < 0 or b0 > rho2 else cid[k0]
            lane_d[0] = -1.0 if k0 < 0 else (b0 if b0 <= rho2 else float(cid[k0]))
            lane_j[1] = -2 if k1 < 0 or b1 > rho2 else cid[k1]
            lane_d[1] = -1.0 if k1 < 0 else (b1 if b1 <= rho2 else float(cid[k1]))
            lane_j[2] = -2 if k2 < 0 or b2 > rho2 else cid[k2]
            lane_d[2] = -1.0 if k2 < 0 else (b2 if b2 <= rho2 else float(cid[k2]))
            lane_j[3] = -2 if k3 < 0 or b3 > rho2 else cid[k3]
            lane_d[3] = -1.0 if k3 < 0 else (b3 if b3 <= rho2 else float(cid[k3]))
        for k in range(run):
            j = lane_j[k]
            d2 = lane_d[k]
            if j == -2:
                j, d2 = grid_nearest(
                    lane_x[k], lane_y[k], int(d2), nn[i + k], last, start, spts, x0, y0,
                    cell, nx, ny, max_d2,
                )  # fmt: skip
            elif d2 > max_d2:
                j = -1
                d2 = np.inf
            nn[i + k] = j
            d2s[i + k] = d2
            if j >= 0:
                last = j
        i += run


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def nn_pass(
    src: NDArray[np.float64],
    x: float,
    y: float,
    th: float,
    grid: Grid,
    cover: Cover,
    max_d2: float,
    nn: NDArray[np.int64],
    d2s: NDArray[np.float64],
    chunks: int,
) -> None:
    """`nn_chunk` over all source points, cut into ``chunks`` blocks run in parallel.

    Neighbours are exact whatever the hints, so ``nn`` and ``d2s`` are the same as the
    serial pass's (up to exact ties).
    """
    n = src.shape[0]
    step = (n + chunks - 1) // chunks
    for k in prange(chunks):
        lo = k * step
        nn_chunk(src, x, y, th, grid, cover, max_d2, nn, d2s, lo, min(n, lo + step))


@njit(cache=True, error_model="numpy", nogil=True)
def _p2p_update(
    src: NDArray[np.float64],
    spts: NDArray[np.float64],
    nn: NDArray[np.int64],
    x: float,
    y: float,
    th: float,
) -> tuple[int, float, float, float]:
    """Pairs count and point-to-point update ``(m, dtx, dty, dth)`` (sums in source order)."""
    c = math.cos(th)
    s = math.sin(th)
    m = 0
    spx = 0.0
    spy = 0.0
    sqx = 0.0
    sqy = 0.0
    sxx = 0.0
    sxy = 0.0
    syx = 0.0
    syy = 0.0
    for i in range(src.shape[0]):
        j = nn[i]
        if j < 0:
            continue
        px = c * src[i, 0] - s * src[i, 1] + x
        py = s * src[i, 0] + c * src[i, 1] + y
        qx = spts[j, 0]
        qy = spts[j, 1]
        m += 1
        spx += px
        spy += py
        sqx += qx
        sqy += qy
        sxx += px * qx
        sxy += px * qy
        syx += py * qx
        syy += py * qy
    if m < 3:
        return m, 0.0, 0.0, 0.0
    dtx, dty, dth = _p2p_step(m, spx, spy, sqx, sqy, sxx, sxy, syx, syy)
    return m, dtx, dty, dth


@njit(cache=True, error_model="numpy", nogil=True)
def _solve3(h: NDArray[np.float64], g: NDArray[np.float64]) -> NDArray[np.float64]:
    # Levenberg damping keeps degenerate (corridor) systems solvable; the step along a
    # degenerate direction then stays ~0 instead of exploding.
    lam = 1e-9 * (h[0, 0] + h[1, 1] + h[2, 2]) + 1e-12
    a = h.copy()
    for k in range(3):
        a[k, k] += lam
    det = (
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )
    out = np.zeros(3)
    if det == 0.0 or not math.isfinite(det):
        return out
    inv = np.empty((3, 3))
    inv[0, 0] = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    inv[0, 1] = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
    inv[0, 2] = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    inv[1, 0] = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    inv[1, 1] = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    inv[1, 2] = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    inv[2, 0] = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    inv[2, 1] = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    inv[2, 2] = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    for r in range(3):
        out[r] = -(inv[r, 0] * g[0] + inv[r, 1] * g[1] + inv[r, 2] * g[2]) / det
    return out


@njit(cache=True, error_model="numpy", nogil=True)
def _pl_update(
    src: NDArray[np.float64],
    grid: Grid,
    normals: NDArray[np.float64],
    nn: NDArray[np.int64],
    dnn: NDArray[np.float64],
    x: float,
    y: float,
    th: float,
    trim_fraction: float,
    huber: float,
    radius: float,
    min_nb: int,
    bcache: NDArray[np.float64],
    d2s: NDArray[np.float64],
    res: NDArray[np.float64],
    jac: NDArray[np.float64],
) -> tuple[int, float, float, float]:
    """Pairs count and point-to-line update ``(m, dtx, dty, dth)`` (Censi 2008 metric).

    Each pair's residual is the distance from the source point to the line through its
    neighbour (normal by PCA, computed lazily into ``normals``); ``d2s``, ``res`` and ``jac``
    are work buffers of the source's length.
    """
    start, spts, x0, y0, cell, nx, ny = grid
    c = math.cos(th)
    s = math.sin(th)
    m = 0
    for i in range(src.shape[0]):
        j = nn[i]
        if j < 0:
            continue
        px = c * src[i, 0] - s * src[i, 1] + x
        py = s * src[i, 0] + c * src[i, 1] + y
        if math.isnan(normals[j, 0]):
            a, b, _p = cached_normal(j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache)
            if math.isnan(a):
                a, b, _p = point_normal(
                    j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache
                )
            normals[j, 0] = a
            normals[j, 1] = b
        nnx = normals[j, 0]
        nny = normals[j, 1]
        if nnx == 0.0 and nny == 0.0:
            continue
        d2s[m] = dnn[i]
        res[m] = nnx * (px - spts[j, 0]) + nny * (py - spts[j, 1])
        jac[m, 0] = nnx
        jac[m, 1] = nny
        jac[m, 2] = -nnx * py + nny * px
        m += 1
    if m < 3:
        return m, 0.0, 0.0, 0.0
    dtx, dty, dth = _pl_step(m, d2s, res, jac, trim_fraction, huber)
    return m, dtx, dty, dth


@njit(cache=True, error_model="numpy", nogil=True)
def final_stats(
    src: NDArray[np.float64],
    grid: Grid,
    cover: Cover,
    normals: NDArray[np.float64],
    pose: NDArray[np.float64],
    inlier_thr: float,
    nn: NDArray[np.int64],
    radius: float,
    min_nb: int,
    bcache: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """Nearest-neighbour distances at ``pose``, and the information matrix over inliers.

    ``nn`` holds the last correspondences (search hints); ``normals`` is a lazily filled
    cache (NaN = not computed yet), shared with the point-to-line loop. Neighbours are exact
    at any distance.

    Returns:
        ``(distances (n,), hessian (3, 3), n_inliers)``.
    """
    n = src.shape[0]
    start, spts, x0, y0, cell, nx, ny = grid
    dist = np.empty(n)
    nn_chunk(src, pose[0], pose[1], pose[2], grid, cover, np.inf, nn, dist, 0, n)
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    h = np.zeros((3, 3))
    n_in = 0
    thr2 = inlier_thr * inlier_thr
    for i in range(n):
        d2 = dist[i]
        dist[i] = math.sqrt(d2)
        if d2 < thr2:
            j = nn[i]
            n_in += 1
            if math.isnan(normals[j, 0]):
                a, b, _p = cached_normal(
                    j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache
                )
                if math.isnan(a):
                    a, b, _p = point_normal(
                        j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache
                    )
                normals[j, 0] = a
                normals[j, 1] = b
            nnx = normals[j, 0]
            nny = normals[j, 1]
            if nnx == 0.0 and nny == 0.0:
                continue
            px = c * src[i, 0] - s * src[i, 1] + pose[0]
            py = s * src[i, 0] + c * src[i, 1] + pose[1]
            jv0 = nnx
            jv1 = nny
            jv2 = -nnx * py + nny * px
            h[0, 0] += jv0 * jv0
            h[0, 1] += jv0 * jv1
            h[0, 2] += jv0 * jv2
            h[1, 1] += jv1 * jv1
            h[1, 2] += jv1 * jv2
            h[2, 2] += jv2 * jv2
    h[1, 0] = h[0, 1]
    h[2, 0] = h[0, 2]
    h[2, 1] = h[1, 2]
    return dist, h, n_in


@njit(cache=True, error_model="numpy", nogil=True)
def _setup(
    tgt: NDArray[np.float64], cell_size: float, n: int, starts: int, radius: float, min_nb: int
) -> tuple[Grid, Cover, NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Grid, cover and block normals of the target, and the per-match caches.

    ``n`` source points are matched from ``starts`` initial poses.
    """
    cell = choose_cell_size(tgt, cell_size)
    start, _order, spts, gx0, gy0, gnx, gny = build_grid(tgt, cell)
    grid = (start, spts, gx0, gy0, cell, gnx, gny)
    # a local map against one scan: the grid alone answers faster, and few blocks are read
    large = tgt.shape[0] > COVER_MAX_TARGET_RATIO * n * starts
    # (the spacing estimate needs the points in scan order, the cover the sorted ones)
    cover = no_cover() if large else build_cover(spts, cover_radius(tgt))
    nn = np.full(n, -1, dtype=np.int64)
    # per target point, filled on demand (only points that get paired need one)
    normals = np.full((tgt.shape[0], 2), np.nan)
    if cell <= radius and large:
        bcache = pending_block_normals(start, spts.shape[0], gnx * gny)
    elif cell <= radius:
        bcache = block_normals(start, spts, gx0, gy0, cell, gnx, gny, min_nb)
    else:
        bcache = np.full((1, 4, 3), np.nan)  # unused: every normal comes from a disc
    return grid, cover, nn, normals, bcache


@njit(cache=True, error_model="numpy", nogil=True)
def _finish(
    x: float,
    y: float,
    th: float,
    iters: int,
    converged: bool,
    status: int,
    src: NDArray[np.float64],
    grid: Grid,
    cover: Cover,
    normals: NDArray[np.float64],
    inlier_thr: float,
    nn: NDArray[np.int64],
    radius: float,
    min_nb: int,
    bcache: NDArray[np.float64],
) -> MatchTuple:
    """Final-alignment statistics, or empty ones when the loop failed.

    Returns ``(x, y, theta, iterations, converged, status, mean distance, median distance,
    hessian, its eigenvalues (ascending, clipped at 0), n_inliers)``.
    """
    if status != STATUS_OK:
        return (
            x, y, th, iters, converged, status, np.nan, np.nan, np.zeros((3, 3)), np.zeros(3),
            0,
        )  # fmt: skip
    pose = np.array([x, y, th])
    dist, hess, n_in = final_stats(
        src, grid, cover, normals, pose, inlier_thr, nn, radius, min_nb, bcache
    )
    # here rather than in Python: numpy's per-call overhead on 3x3 and 1-D reductions is
    # ~30-60 us per match
    eig = np.maximum(np.linalg.eigvalsh(hess), 0.0)
    return x, y, th, iters, converged, status, dist.mean(), median(dist), hess, eig, n_in


def _make_runner(point_to_line: bool, threaded: bool) -> Any:
    """The compiled match for one (metric, threading) combination: `run_match` picks it.

    ``point_to_line`` and ``threaded`` are closure constants, so numba prunes the other
    branches before compiling (and keys its cache on them): a process that only runs the
    paper's point-to-point ICP never compiles the point-to-line update nor the parallel
    search, which halves the first (cold-cache) match from ~40 s.

    The kernel's only closure variables are these two booleans: numba keys a closure's cache
    entry on its pickled closure variables, and a captured dispatcher pickles differently in
    every process (a new cache file per process, never reused), so the ICP loop is written
    inline rather than as a second closure kernel.
    """

    @njit(cache=True, error_model="numpy", nogil=True)
    def run(
        src: NDArray[np.float64],
        tgt: NDArray[np.float64],
        inits: NDArray[np.float64],
        cell_size: float,
        max_iter: int,
        tol_t: float,
        tol_r: float,
        paper_rule: bool,
        max_d2: float,
        trim_fraction: float,
        huber: float,
        radius: float,
        min_nb: int,
        inlier_thr: float,
        threads: int,
    ) -> list[MatchTuple]:
        """Grid and cover of the target, the ICP iterations, the final statistics.

        The iterations: exact nearest-neighbour pairs, one update, until the stop rule.
        Point-to-point (the paper's): centred cross-covariance and its Procrustes rotation.
        The rotation of each update is the SVD solution ``R = U V^T`` (with the reflection
        fix) of the 2x2 cross-covariance; in 2D it has the closed form
        ``theta = atan2(sum(p x q), sum(p . q))`` over centred pairs, used here for speed
        (the numpy reference in ``scanguard.matching.reference`` uses the SVD and agrees to
        1e-9). Point-to-line (Censi 2008 metric): the closest ``trim_fraction`` of pairs,
        Huber weights, one Gauss-Newton step.

        The search of each iteration is `nn_chunk`, or the parallel `nn_pass` in ``threads``
        blocks; the sums are always serial, in source order, so the result does not depend
        on ``threads`` or on thread timing. ``nn`` holds per source point its last neighbour
        (a search hint, -1: none), updated in place.

        One match per row of ``inits`` (``(S, 3)`` initial poses), in a list: the target's
        grid, cover and normals are built once and shared (a second start against a
        10,000-point local map saves ~0.4 ms of its ~1.8 ms). Each start begins with the
        hints reset, as a match of its own would; the normals are a function of the target
        alone, so filling them in during an earlier start changes nothing later.
        """
        grid, cover, nn, normals, bcache = _setup(
            tgt, cell_size, src.shape[0], inits.shape[0], radius, min_nb
        )
        n = src.shape[0]
        spts = grid[1]
        dnn = np.empty(n)
        d2s = np.empty(n)
        res = np.empty(n)
        jac = np.empty((n, 3))
        out = []
        for start in range(inits.shape[0]):
            nn[:] = -1
            x = inits[start, 0]
            y = inits[start, 1]
            th = inits[start, 2]
            it = 0
            converged = False
            status = STATUS_OK
            while it < max_iter:
                it += 1
                if threaded:
                    nn_pass(src, x, y, th, grid, cover, max_d2, nn, dnn, threads)
                else:
                    nn_chunk(src, x, y, th, grid, cover, max_d2, nn, dnn, 0, n)
                if point_to_line:
                    m, dtx, dty, dth = _pl_update(
                        src, grid, normals, nn, dnn, x, y, th, trim_fraction, huber, radius,
                        min_nb, bcache, d2s, res, jac,
                    )  # fmt: skip
                else:
                    m, dtx, dty, dth = _p2p_update(src, spts, nn, x, y, th)
                if m < 3:
                    status = STATUS_FEW_PAIRS
                    break
                x, y, th, status, converged = _apply_step(
                    x, y, th, dtx, dty, dth, tol_t, tol_r, paper_rule
                )
                if status != STATUS_OK or converged:
                    break
            out.append(
                _finish(
                    x, y, th, it, converged, status, src, grid, cover, normals, inlier_thr, nn,
                    radius, min_nb, bcache,
                )
            )  # fmt: skip
        return out

    return run


_RUNNERS = {
    (point_to_line, threaded): _make_runner(point_to_line, threaded)
    for point_to_line in (False, True)
    for threaded in (False, True)
}


def run_match(
    point_to_line: bool,
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    inits: NDArray[np.float64],
    cell_size: float,
    max_iter: int,
    tol_t: float,
    tol_r: float,
    paper_rule: bool,
    max_d2: float,
    trim_fraction: float,
    huber: float,
    radius: float,
    min_nb: int,
    inlier_thr: float,
    threads: int,
) -> list[MatchTuple]:
    """Whole matches in compiled code: grid, cover, ICP loop, final statistics.

    One compiled call instead of several saves the per-call dispatch and the allocations in
    Python, which cost as much as a few iterations. ``threads > 1`` runs the search of each
    iteration in that many parallel chunks; the final statistics stay serial.

    ``inits`` holds the initial poses, ``(3,)`` or ``(S, 3)``: one match from each, against
    the same target built once; each result is the one a match from that pose alone gives.
    The other arguments are the compiled runner's (see `_make_runner`).

    Returns:
        One `MatchTuple` per initial pose; the statistics are NaN/zero unless
        ``status == STATUS_OK``.
    """
    run = _RUNNERS[(bool(point_to_line), threads > 1)]
    out: list[MatchTuple] = run(
        src, tgt, np.ascontiguousarray(inits, dtype=np.float64).reshape(-1, 3), cell_size,
        max_iter, tol_t, tol_r, paper_rule, max_d2, trim_fraction, huber, radius, min_nb,
        inlier_thr, threads,
    )  # fmt: skip
    return out
