"""Numba ICP loops (point-to-point, point-to-line) and the final-alignment statistics.

Status codes returned by the loops: 0 = ran, 1 = too few pairs, 2 = estimate diverged.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from scanguard.matching._grid import (
    Cover,
    Grid,
    build_cover,
    build_grid,
    choose_cell_size,
    cover_nearest,
    cover_radius,
    grid_nearest,
    point_normal,
)

STATUS_OK = 0
STATUS_FEW_PAIRS = 1
STATUS_DIVERGED = 2


@njit(cache=True)
def all_finite(a: NDArray[np.float64]) -> bool:
    """Whether every entry of ``a`` (2-D) is finite; one pass, no temporaries."""
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            if not math.isfinite(a[i, k]):
                return False
    return True


@njit(cache=True)
def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
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
        cut = np.partition(d2s[:m], keep - 1)[keep - 1]
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


@njit(cache=True, inline="always")
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


@njit(cache=True)
def p2p_loop(
    src: NDArray[np.float64],
    grid: Grid,
    cover: Cover,
    init: NDArray[np.float64],
    max_iter: int,
    tol_t: float,
    tol_r: float,
    paper_rule: bool,
    max_d2: float,
    nn: NDArray[np.int64],
) -> tuple[float, float, float, int, bool, int]:
    """The paper's ICP: NN pairs, centred cross-covariance, Procrustes rotation, iterate.

    The rotation of each update is the SVD solution ``R = U V^T`` (with the reflection fix) of
    the 2x2 cross-covariance; in 2D it has the closed form
    ``theta = atan2(sum(p x q), sum(p . q))`` over centred pairs, used here for speed (the
    numpy reference in ``scanguard.matching.reference`` uses the SVD and agrees to 1e-9).

    ``nn`` holds per source point its last neighbour (a search hint, -1: none), updated in
    place.
    """
    x = init[0]
    y = init[1]
    th = init[2]
    n = src.shape[0]
    start, spts, x0, y0, cell, nx, ny = grid
    cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2 = cover
    it = 0
    converged = False
    status = STATUS_OK
    while it < max_iter:
        it += 1
        c = math.cos(th)
        s = math.sin(th)
        m = 0
        last = -1
        spx = 0.0
        spy = 0.0
        sqx = 0.0
        sqy = 0.0
        sxx = 0.0
        sxy = 0.0
        syx = 0.0
        syy = 0.0
        for i in range(n):
            px = c * src[i, 0] - s * src[i, 1] + x
            py = s * src[i, 0] + c * src[i, 1] + y
            j, _d2 = cover_nearest(px, py, cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2)
            if j == -2:
                j, _d2 = grid_nearest(
                    px, py, int(_d2), nn[i], last, start, spts, x0, y0, cell, nx, ny, max_d2
                )
            elif _d2 > max_d2:
                j = -1
                _d2 = np.inf
            nn[i] = j
            if j < 0:
                continue
            last = j
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
            status = STATUS_FEW_PAIRS
            break
        dtx, dty, dth = _p2p_step(m, spx, spy, sqx, sqy, sxx, sxy, syx, syy)
        x, y, th, status, converged = _apply_step(x, y, th, dtx, dty, dth, tol_t, tol_r, paper_rule)
        if status != STATUS_OK or converged:
            break
    return x, y, th, it, converged, status


@njit(cache=True, parallel=True)
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
    """Exact nearest neighbours of all source points at pose ``(x, y, th)``, in parallel.

    The source points are cut into ``chunks`` contiguous blocks, one ``prange`` iteration
    each; within a block the search hints are those of the serial loops (the point's last
    neighbour, the previous point's neighbour), reset at the block start. Hints only speed
    the search up, so ``nn`` (index, -1: none within ``max_d2``) and ``d2s`` (squared
    distance) are the same as in the serial loops (up to exact ties), updated in place.
    """
    n = src.shape[0]
    start, spts, x0, y0, cell, nx, ny = grid
    cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2 = cover
    c = math.cos(th)
    s = math.sin(th)
    step = (n + chunks - 1) // chunks
    for k in prange(chunks):
        lo = k * step
        hi = min(n, lo + step)
        last = -1
        for i in range(lo, hi):
            px = c * src[i, 0] - s * src[i, 1] + x
            py = s * src[i, 0] + c * src[i, 1] + y
            j, d2 = cover_nearest(px, py, cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2)
            if j == -2:
                j, d2 = grid_nearest(
                    px, py, int(d2), nn[i], last, start, spts, x0, y0, cell, nx, ny, max_d2
                )
            elif d2 > max_d2:
                j = -1
                d2 = np.inf
            nn[i] = j
            d2s[i] = d2
            if j >= 0:
                last = j


@njit(cache=True)
def p2p_loop_mt(
    src: NDArray[np.float64],
    grid: Grid,
    cover: Cover,
    init: NDArray[np.float64],
    max_iter: int,
    tol_t: float,
    tol_r: float,
    paper_rule: bool,
    max_d2: float,
    nn: NDArray[np.int64],
    chunks: int,
) -> tuple[float, float, float, int, bool, int]:
    """`p2p_loop` with the nearest-neighbour search of each iteration in parallel.

    The cross-covariance sums are then accumulated serially in source order, with the same
    arithmetic as `p2p_loop`: the reduction is deterministic and, since the neighbours are
    exact, the result is bit-identical to the serial loop's (exact ties aside), whatever the
    number of chunks and threads. The serial pass costs ~2 us of the ~40-130 us iteration.
    """
    x = init[0]
    y = init[1]
    th = init[2]
    n = src.shape[0]
    spts = grid[1]
    d2s = np.empty(n)
    it = 0
    converged = False
    status = STATUS_OK
    while it < max_iter:
        it += 1
        nn_pass(src, x, y, th, grid, cover, max_d2, nn, d2s, chunks)
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
        for i in range(n):
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
            status = STATUS_FEW_PAIRS
            break
        dtx, dty, dth = _p2p_step(m, spx, spy, sqx, sqy, sxx, sxy, syx, syy)
        x, y, th, status, converged = _apply_step(x, y, th, dtx, dty, dth, tol_t, tol_r, paper_rule)
        if status != STATUS_OK or converged:
            break
    return x, y, th, it, converged, status


@njit(cache=True)
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


@njit(cache=True)
def pl_loop(
    src: NDArray[np.float64],
    grid: Grid,
    cover: Cover,
    normals: NDArray[np.float64],
    init: NDArray[np.float64],
    max_iter: int,
    tol_t: float,
    tol_r: float,
    paper_rule: bool,
    max_d2: float,
    trim_fraction: float,
    huber: float,
    radius: float,
    min_nb: int,
    bcache: NDArray[np.float64],
    nn: NDArray[np.int64],
) -> tuple[float, float, float, int, bool, int]:
    """Point-to-line ICP (Censi 2008 metric) with trimming and a Huber kernel.

    Each source point is paired with its nearest target point; the residual is the distance
    to the target's local line (normal from PCA). The closest ``trim_fraction`` of pairs are
    kept, weighted by Huber, and one Gauss-Newton step in ``(x, y, theta)`` is taken.
    """
    x = init[0]
    y = init[1]
    th = init[2]
    n = src.shape[0]
    start, spts, x0, y0, cell, nx, ny = grid
    cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2 = cover
    d2s = np.empty(n)
    res = np.empty(n)
    jac = np.empty((n, 3))
    it = 0
    converged = False
    status = STATUS_OK
    while it < max_iter:
        it += 1
        c = math.cos(th)
        s = math.sin(th)
        m = 0
        last = -1
        for i in range(n):
            px = c * src[i, 0] - s * src[i, 1] + x
            py = s * src[i, 0] + c * src[i, 1] + y
            j, d2 = cover_nearest(px, py, cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2)
            if j == -2:
                j, d2 = grid_nearest(
                    px, py, int(d2), nn[i], last, start, spts, x0, y0, cell, nx, ny, max_d2
                )
            elif d2 > max_d2:
                j = -1
                d2 = np.inf
            nn[i] = j
            if j < 0:
                continue
            last = j
            if math.isnan(normals[j, 0]):
                a, b, _p = point_normal(
                    j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache
                )
                normals[j, 0] = a
                normals[j, 1] = b
            nnx = normals[j, 0]
            nny = normals[j, 1]
            if nnx == 0.0 and nny == 0.0:
                continue
            d2s[m] = d2
            res[m] = nnx * (px - spts[j, 0]) + nny * (py - spts[j, 1])
            jac[m, 0] = nnx
            jac[m, 1] = nny
            jac[m, 2] = -nnx * py + nny * px
            m += 1
        if m < 3:
            status = STATUS_FEW_PAIRS
            break
        dtx, dty, dth = _pl_step(m, d2s, res, jac, trim_fraction, huber)
        x, y, th, status, converged = _apply_step(x, y, th, dtx, dty, dth, tol_t, tol_r, paper_rule)
        if status != STATUS_OK or converged:
            break
    return x, y, th, it, converged, status


@njit(cache=True)
def pl_loop_mt(
    src: NDArray[np.float64],
    grid: Grid,
    cover: Cover,
    normals: NDArray[np.float64],
    init: NDArray[np.float64],
    max_iter: int,
    tol_t: float,
    tol_r: float,
    paper_rule: bool,
    max_d2: float,
    trim_fraction: float,
    huber: float,
    radius: float,
    min_nb: int,
    bcache: NDArray[np.float64],
    nn: NDArray[np.int64],
    chunks: int,
) -> tuple[float, float, float, int, bool, int]:
    """`pl_loop` with the nearest-neighbour search of each iteration in parallel.

    Normals (a lazily filled cache), residuals and the Gauss-Newton sums are then computed
    serially in source order with the same arithmetic as `pl_loop`, so the result is
    bit-identical to the serial loop's (exact ties aside) and deterministic.
    """
    x = init[0]
    y = init[1]
    th = init[2]
    n = src.shape[0]
    start, spts, x0, y0, cell, nx, ny = grid
    d2s = np.empty(n)
    dnn = np.empty(n)
    res = np.empty(n)
    jac = np.empty((n, 3))
    it = 0
    converged = False
    status = STATUS_OK
    while it < max_iter:
        it += 1
        nn_pass(src, x, y, th, grid, cover, max_d2, nn, dnn, chunks)
        c = math.cos(th)
        s = math.sin(th)
        m = 0
        for i in range(n):
            j = nn[i]
            if j < 0:
                continue
            px = c * src[i, 0] - s * src[i, 1] + x
            py = s * src[i, 0] + c * src[i, 1] + y
            d2 = dnn[i]
            if math.isnan(normals[j, 0]):
                a, b, _p = point_normal(
                    j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache
                )
                normals[j, 0] = a
                normals[j, 1] = b
            nnx = normals[j, 0]
            nny = normals[j, 1]
            if nnx == 0.0 and nny == 0.0:
                continue
            d2s[m] = d2
            res[m] = nnx * (px - spts[j, 0]) + nny * (py - spts[j, 1])
            jac[m, 0] = nnx
            jac[m, 1] = nny
            jac[m, 2] = -nnx * py + nny * px
            m += 1
        if m < 3:
            status = STATUS_FEW_PAIRS
            break
        dtx, dty, dth = _pl_step(m, d2s, res, jac, trim_fraction, huber)
        x, y, th, status, converged = _apply_step(x, y, th, dtx, dty, dth, tol_t, tol_r, paper_rule)
        if status != STATUS_OK or converged:
            break
    return x, y, th, it, converged, status


@njit(cache=True)
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
    cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2 = cover
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    dist = np.empty(n)
    h = np.zeros((3, 3))
    n_in = 0
    thr2 = inlier_thr * inlier_thr
    last = -1
    for i in range(n):
        px = c * src[i, 0] - s * src[i, 1] + pose[0]
        py = s * src[i, 0] + c * src[i, 1] + pose[1]
        j, d2 = cover_nearest(px, py, cs, cx, cy, cid, cx0, cy0, cinv, cnx, cny, rho2)
        if j == -2:
            j, d2 = grid_nearest(
                px, py, int(d2), nn[i], last, start, spts, x0, y0, cell, nx, ny, np.inf
            )
        last = j
        dist[i] = math.sqrt(d2)
        if d2 < thr2:
            n_in += 1
            if math.isnan(normals[j, 0]):
                a, b, _p = point_normal(
                    j, start, spts, x0, y0, cell, nx, ny, radius, min_nb, bcache
                )
                normals[j, 0] = a
                normals[j, 1] = b
            nnx = normals[j, 0]
            nny = normals[j, 1]
            if nnx == 0.0 and nny == 0.0:
                continue
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


@njit(cache=True)
def _setup(
    tgt: NDArray[np.float64], cell_size: float, n: int
) -> tuple[Grid, Cover, NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Grid and cover of the target and the per-match caches (serial and threaded runs)."""
    cell = choose_cell_size(tgt, cell_size)
    start, _order, spts, gx0, gy0, gnx, gny = build_grid(tgt, cell)
    grid = (start, spts, gx0, gy0, cell, gnx, gny)
    # the spacing estimate needs the points in scan order, the cover the sorted ones
    cover = build_cover(spts, cover_radius(tgt))
    m = tgt.shape[0]
    nn = np.full(n, -1, dtype=np.int64)
    # normals are computed on demand, only for target points that get paired
    normals = np.full((m, 2), np.nan)
    bcache = np.full((m, 4, 3), np.nan)
    return grid, cover, nn, normals, bcache


@njit(cache=True)
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
) -> tuple[
    float, float, float, int, bool, int, NDArray[np.float64], float, NDArray[np.float64], int
]:
    """Final-alignment statistics, or empty ones when the loop failed."""
    if status != STATUS_OK:
        return x, y, th, iters, converged, status, np.empty(0), np.nan, np.zeros((3, 3)), 0
    pose = np.array([x, y, th])
    dist, hess, n_in = final_stats(
        src, grid, cover, normals, pose, inlier_thr, nn, radius, min_nb, bcache
    )
    med = np.median(dist)
    return x, y, th, iters, converged, status, dist, med, hess, n_in


@njit(cache=True)
def run_match(
    point_to_line: bool,
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    init: NDArray[np.float64],
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
) -> tuple[
    float, float, float, int, bool, int, NDArray[np.float64], float, NDArray[np.float64], int
]:
    """One whole match in compiled code (serial): grid, cover, ICP loop, final statistics.

    One call instead of several saves the per-call dispatch and the allocations in Python,
    which cost as much as a few iterations. The threaded variant is the separate
    `run_match_mt`, so that the serial path never compiles the parallel kernels (a cold numba
    cache would otherwise spend ~30 s on them at the first match).

    Returns:
        ``(x, y, theta, iterations, converged, status, distances, median distance,
        hessian, n_inliers)``; the last four are empty/zero unless ``status == STATUS_OK``.
    """
    grid, cover, nn, normals, bcache = _setup(tgt, cell_size, src.shape[0])
    if point_to_line:
        x, y, th, iters, converged, status = pl_loop(
            src, grid, cover, normals, init, max_iter, tol_t, tol_r, paper_rule, max_d2,
            trim_fraction, huber, radius, min_nb, bcache, nn,
        )  # fmt: skip
    else:
        x, y, th, iters, converged, status = p2p_loop(
            src, grid, cover, init, max_iter, tol_t, tol_r, paper_rule, max_d2, nn
        )
    return _finish(
        x, y, th, iters, converged, status, src, grid, cover, normals, inlier_thr, nn, radius,
        min_nb, bcache,
    )  # fmt: skip


@njit(cache=True)
def run_match_mt(
    point_to_line: bool,
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    init: NDArray[np.float64],
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
) -> tuple[
    float, float, float, int, bool, int, NDArray[np.float64], float, NDArray[np.float64], int
]:
    """`run_match` with the nearest-neighbour search of every iteration in ``threads`` chunks."""
    grid, cover, nn, normals, bcache = _setup(tgt, cell_size, src.shape[0])
    if point_to_line:
        x, y, th, iters, converged, status = pl_loop_mt(
            src, grid, cover, normals, init, max_iter, tol_t, tol_r, paper_rule, max_d2,
            trim_fraction, huber, radius, min_nb, bcache, nn, threads,
        )  # fmt: skip
    else:
        x, y, th, iters, converged, status = p2p_loop_mt(
            src, grid, cover, init, max_iter, tol_t, tol_r, paper_rule, max_d2, nn, threads
        )
    return _finish(
        x, y, th, iters, converged, status, src, grid, cover, normals, inlier_thr, nn, radius,
        min_nb, bcache,
    )  # fmt: skip
