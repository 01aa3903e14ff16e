"""Quality of a match: GMapping's likelihood score of the current scan against the previous one.

`gmapping_features` / `gmapping_score` evaluate ``ScanMatcher::score`` of OpenSLAM GMapping with
the previous scan as the map: for every endpoint of the current scan, moved by the match
estimate, the best Gaussian likelihood of a nearby previous endpoint whose "free" cell
(``sqrt(2)`` cells before the endpoint along the beam) is free too. It is a property of the
match, so it lives with the matchers; the classical detectors and the dataset read it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import ConfigError, ScanError
from scanguard.scan import LaserScan

FloatArray = NDArray[np.float64]

# GMapping's ``m_freeCellRatio``: the "free" cell is sqrt(2) cells before the beam endpoint.
_FREE_CELL_RATIO = math.sqrt(2.0)
# Largest bounding box (in cells) for which the score uses a dense lookup table (32 MB).
_DENSE_CELLS = 4_000_000


# --------------------------------------------------------------------------------------------
# GMapping-style likelihood score
# --------------------------------------------------------------------------------------------


def _points(points: LaserScan | ArrayLike, what: str, max_range: float | None) -> FloatArray:
    raw = points.points(np.float64) if isinstance(points, LaserScan) else points
    pts: FloatArray = np.asarray(raw, dtype=np.float64)
    if pts.size == 0:
        return np.empty((0, 2))
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ScanError(f"gmapping_score: {what} points must have shape (N, 2), got {pts.shape}")
    # per column: numpy reductions over a trailing axis of length 2 are slow
    keep = np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1])
    if max_range is not None:
        keep &= np.hypot(pts[:, 0], pts[:, 1]) <= max_range
    return pts if keep.all() else pts[keep]


def _cell_keys(ix: NDArray[np.int64], iy: NDArray[np.int64]) -> NDArray[np.int64]:
    # Offsetting by 2**30 keeps keys non-negative and unique for |cell index| < 2**30.
    return (ix + (1 << 30)) * (1 << 31) + (iy + (1 << 30))


_GMAPPING_ZERO = {"gmapping_score": 0.0, "gmapping_score_norm": 0.0, "gmapping_matched": 0.0}


def _gmapping_inputs(
    previous: LaserScan | ArrayLike,
    current: LaserScan | ArrayLike,
    pose: ArrayLike,
    sigma: float,
    kernel_size: int,
    resolution: float,
    max_range: float | None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Checked parameters; finite, in-range previous and current points and the pose."""
    if sigma <= 0 or resolution <= 0 or kernel_size < 0:
        raise ConfigError(
            f"gmapping_score: sigma ({sigma}) and resolution ({resolution}) must be > 0 and "
            f"kernel_size ({kernel_size}) >= 0"
        )
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ScanError(f"gmapping_score: pose must be 3 finite numbers, got {p!r}")
    prev = np.ascontiguousarray(_points(previous, "previous", max_range))
    cur_local = np.ascontiguousarray(_points(current, "current", max_range))
    return prev, cur_local, p


# Empty-slot marker of the compiled kernel's cell hash table (no real cell index comes near it).
_NO_CELL = np.iinfo(np.int64).min
# Largest bounding box (in cells) for which the compiled kernel uses a dense table (2 MB of
# int32, cleared per call: larger boxes cost more to clear than the hash lookups they save).
_KERNEL_DENSE_CELLS = 1 << 19


@njit(cache=True, nogil=True)
def _hash_slot(keys: NDArray[np.int64], ix: int, iy: int) -> int:
    """Slot of cell ``(ix, iy)`` in the open-addressing table: its own, or the empty one to use.

    ``keys[slot] = (ix, iy)``, ``ix = _NO_CELL`` when empty; the table is a power of two long.
    """
    mask = keys.shape[0] - 1
    # Multiplicative hashing of both indices (int64 products wrap), then linear probing.
    h = ix * -7046029254386353131 + iy * -4658895280553007687
    i = (h >> 40) & mask
    while keys[i, 0] != _NO_CELL and (keys[i, 0] != ix or keys[i, 1] != iy):
        i = (i + 1) & mask
    return i


@njit(cache=True, nogil=True)
def _endpoint(
    lx: float,
    ly: float,
    c: float,
    s: float,
    px: float,
    py: float,
    resolution: float,
    back_dist: float,
) -> tuple[float, float, int, int, int, int]:
    """Endpoint moved into the previous frame, its cell and its free-cell offset (in cells)."""
    x = lx * c + ly * -s + px
    y = lx * s + ly * c + py
    cx0 = int(np.floor(x / resolution))
    cy0 = int(np.floor(y / resolution))
    rx = x - px
    ry = y - py
    rng = max(np.hypot(rx, ry), 1e-12)
    back = max(rng - back_dist, 0.0) / rng
    fx = int(np.floor((px + rx * back) / resolution)) - cx0
    fy = int(np.floor((py + ry * back) / resolution)) - cy0
    return x, y, cx0, cy0, fx, fy


@njit(cache=True, nogil=True)
def _score_dense(
    prev: FloatArray,
    cur_local: FloatArray,
    pix: NDArray[np.int64],
    piy: NDArray[np.int64],
    pose: FloatArray,
    sigma: float,
    kernel_size: int,
    resolution: float,
    back_dist: float,
) -> tuple[float, int]:
    """`_gmapping_kernel` with a dense cell table over the previous endpoints' bounding box."""
    n = prev.shape[0]
    lox = pix.min()
    loy = piy.min()
    dx = pix.max() - lox + 1
    dy = piy.max() - loy + 1
    table = np.full(dx * dy, -1, dtype=np.int32)
    means = np.zeros((n, 2))
    counts = np.zeros(n)
    n_cells = 0
    for j in range(n):
        slot = (pix[j] - lox) * dy + (piy[j] - loy)
        k = table[slot]
        if k < 0:
            k = n_cells
            table[slot] = k
            n_cells += 1
        # summed in point order, like np.bincount: the same sums, so the same means
        means[k, 0] += prev[j, 0]
        means[k, 1] += prev[j, 1]
        counts[k] += 1.0
    for k in range(n_cells):
        means[k, 0] /= counts[k]
        means[k, 1] /= counts[k]

    px, py = pose[0], pose[1]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    total = 0.0
    n_found = 0
    for m in range(cur_local.shape[0]):
        x, y, cx0, cy0, fx, fy = _endpoint(
            cur_local[m, 0], cur_local[m, 1], c, s, px, py, resolution, back_dist
        )
        best = np.inf
        for ox in range(-kernel_size, kernel_size + 1):
            ax = cx0 + ox - lox
            bx = ax + fx
            for oy in range(-kernel_size, kernel_size + 1):
                ay = cy0 + oy - loy
                if ax < 0 or ax >= dx or ay < 0 or ay >= dy:
                    continue
                k = table[ax * dy + ay]
                if k < 0:
                    continue
                d2 = (x - means[k, 0]) ** 2 + (y - means[k, 1]) ** 2
                # the free-cell test only matters for a cell that would be the new nearest
                if d2 < best:
                    by = ay + fy
                    if bx < 0 or bx >= dx or by < 0 or by >= dy or table[bx * dy + by] < 0:
                        best = d2
        if best < np.inf:
            total += np.exp(-best / sigma)
            n_found += 1
    return total, n_found


@njit(cache=True, nogil=True)
def _score_hashed(
    prev: FloatArray,
    cur_local: FloatArray,
    pix: NDArray[np.int64],
    piy: NDArray[np.int64],
    pose: FloatArray,
    sigma: float,
    kernel_size: int,
    resolution: float,
    back_dist: float,
) -> tuple[float, int]:
    """`_gmapping_kernel` with the cells in a hash table (any extent, O(N) memory)."""
    n = prev.shape[0]
    cap = 16
    while cap < 2 * n:
        cap *= 2
    keys = np.full((cap, 2), _NO_CELL, dtype=np.int64)
    row = np.empty(cap, dtype=np.int32)
    means = np.zeros((n, 2))
    counts = np.zeros(n)
    n_cells = 0
    for j in range(n):
        i = _hash_slot(keys, pix[j], piy[j])
        if keys[i, 0] == _NO_CELL:
            keys[i, 0] = pix[j]
            keys[i, 1] = piy[j]
            row[i] = n_cells
            n_cells += 1
        k = row[i]
        means[k, 0] += prev[j, 0]
        means[k, 1] += prev[j, 1]
        counts[k] += 1.0
    for k in range(n_cells):
        means[k, 0] /= counts[k]
        means[k, 1] /= counts[k]

    px, py = pose[0], pose[1]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    total = 0.0
    n_found = 0
    for m in range(cur_local.shape[0]):
        x, y, cx0, cy0, fx, fy = _endpoint(
            cur_local[m, 0], cur_local[m, 1], c, s, px, py, resolution, back_dist
        )
        best = np.inf
        for ox in range(-kernel_size, kernel_size + 1):
            for oy in range(-kernel_size, kernel_size + 1):
                i = _hash_slot(keys, cx0 + ox, cy0 + oy)
                if keys[i, 0] == _NO_CELL:
                    continue
                k = row[i]
                d2 = (x - means[k, 0]) ** 2 + (y - means[k, 1]) ** 2
                if d2 < best:
                    f = _hash_slot(keys, cx0 + ox + fx, cy0 + oy + fy)
                    if keys[f, 0] == _NO_CELL:
                        best = d2
        if best < np.inf:
            total += np.exp(-best / sigma)
            n_found += 1
    return total, n_found


@njit(cache=True, nogil=True)
def _gmapping_kernel(
    prev: FloatArray,
    cur_local: FloatArray,
    pose: FloatArray,
    sigma: float,
    kernel_size: int,
    resolution: float,
    free_cell_ratio: float,
    dense_cells: int,
) -> tuple[float, int]:
    """Sum of the endpoint likelihoods and number of matched endpoints (see `gmapping_features`).

    Same arithmetic as `_gmapping_features_numpy`, one endpoint at a time, with the cells of
    the previous endpoints in a dense table over their bounding box when it has at most
    ``dense_cells`` cells, else in a hash table (long-range scans): O(N + M * (2k+1)^2).
    """
    n = prev.shape[0]
    pix = np.empty(n, dtype=np.int64)
    piy = np.empty(n, dtype=np.int64)
    for j in range(n):
        pix[j] = int(np.floor(prev[j, 0] / resolution))
        piy[j] = int(np.floor(prev[j, 1] / resolution))
    back_dist = resolution * free_cell_ratio
    n_box = (pix.max() - pix.min() + 1) * (piy.max() - piy.min() + 1)
    if n_box <= dense_cells:
        return _score_dense(
            prev, cur_local, pix, piy, pose, sigma, kernel_size, resolution, back_dist
        )
    return _score_hashed(prev, cur_local, pix, piy, pose, sigma, kernel_size, resolution, back_dist)


def gmapping_features(
    previous: LaserScan | ArrayLike,
    current: LaserScan | ArrayLike,
    pose: ArrayLike,
    *,
    sigma: float = 0.05,
    kernel_size: int = 1,
    resolution: float = 0.05,
    free_cell_ratio: float = _FREE_CELL_RATIO,
    max_range: float | None = None,
) -> dict[str, float]:
    """GMapping-style likelihood of the current scan against the previous one.

    This is GMapping's ``ScanMatcher::score`` with a grid built from the previous scan's
    endpoints as the map: each current endpoint (moved by ``pose`` into the previous sensor
    frame) looks at the ``(2 * kernel_size + 1)^2`` grid cells around its own cell; a cell
    counts if it holds previous endpoints *and* its companion cell ``free_cell_ratio`` cells
    back along the beam does not (GMapping's "occupied, with free space in front" test). The
    endpoint contributes ``exp(-d^2 / sigma)`` where ``d`` is its distance to the mean of the
    nearest such cell (GMapping's ``PointAccumulator::mean``), or nothing when no cell counts.

    GMapping accepts a match when this score exceeds ``minimumScore`` and otherwise falls back to
    odometry — exactly a `ThresholdDetector` on ``gmapping_score`` with direction ``"low"``,
    whose tuned threshold is a learned ``minimumScore``. The raw sum grows with the number of
    beams, so ``gmapping_score_norm`` (mean per current endpoint, in ``[0, 1]``; equivalently
    ``minimumScore / n_beams``) is the variant comparable across sensors.

    Args:
        previous: Previous scan: points ``(N, 2)`` in its sensor frame, or a `LaserScan`.
        current: Current scan: points ``(M, 2)`` in its sensor frame, or a `LaserScan`.
        pose: Match estimate, pose of the current sensor frame in the previous one.
        sigma: GMapping's ``gaussianSigma`` (m^2 in the exponent ``exp(-d^2 / sigma)``;
            GMapping's ROS default is 0.05).
        kernel_size: GMapping's ``kernelSize`` (search window half-width in cells).
        resolution: Grid cell size in metres (GMapping's ``delta``).
        free_cell_ratio: Distance, in cells, from the endpoint back to the free-space cell.
        max_range: Ignore endpoints farther than this from their sensor (GMapping's
            ``usableRange``); None keeps all.

    Returns:
        ``{"gmapping_score": sum, "gmapping_score_norm": sum / n_current,
        "gmapping_matched": fraction of current endpoints that found a cell}``; all 0 when the
        current scan has no points.
    """
    prev, cur_local, p = _gmapping_inputs(
        previous, current, pose, sigma, kernel_size, resolution, max_range
    )
    n_cur = len(cur_local)
    if n_cur == 0 or len(prev) == 0:
        return dict(_GMAPPING_ZERO)
    total, n_found = _gmapping_kernel(
        prev,
        cur_local,
        p,
        float(sigma),
        int(kernel_size),
        float(resolution),
        float(free_cell_ratio),
        min(_DENSE_CELLS, _KERNEL_DENSE_CELLS),
    )
    return {
        "gmapping_score": float(total),
        "gmapping_score_norm": float(total) / n_cur,
        "gmapping_matched": float(n_found) / n_cur,
    }


def gmapping_score(
    previous: LaserScan | ArrayLike,
    current: LaserScan | ArrayLike,
    pose: ArrayLike,
    *,
    sigma: float = 0.05,
    kernel_size: int = 1,
    resolution: float = 0.05,
    free_cell_ratio: float = _FREE_CELL_RATIO,
    max_range: float | None = None,
    normalized: bool = False,
) -> float:
    """GMapping ``ScanMatcher::score`` of the current scan against the previous one.

    See `gmapping_features` for the algorithm and parameters. Higher is better; a low score
    flags a likely fault (GMapping's ``minimumScore`` test).

    Args:
        previous: Previous scan points ``(N, 2)`` or a `LaserScan`.
        current: Current scan points ``(M, 2)`` or a `LaserScan`.
        pose: Match estimate (current sensor pose in the previous sensor frame).
        sigma: GMapping ``gaussianSigma``.
        kernel_size: GMapping ``kernelSize`` in cells.
        resolution: Cell size (m).
        free_cell_ratio: Cells back along the beam to the free-space cell.
        max_range: Ignore endpoints beyond this range (m).
        normalized: Return the mean per current endpoint (in ``[0, 1]``) instead of the sum.

    Returns:
        The score.
    """
    f = gmapping_features(
        previous,
        current,
        pose,
        sigma=sigma,
        kernel_size=kernel_size,
        resolution=resolution,
        free_cell_ratio=free_cell_ratio,
        max_range=max_range,
    )
    return f["gmapping_score_norm"] if normalized else f["gmapping_score"]


#: Cell coordinates ``(cx, cy)`` -> index into the cell means, -1 where no endpoint fell.
_CellLookup = Callable[[NDArray[np.int64], NDArray[np.int64]], NDArray[np.int64]]


def _previous_cells(
    prev: NDArray[np.float64], resolution: float
) -> tuple[NDArray[np.float64], _CellLookup]:
    """The numpy reference's map: cell means of the previous endpoints, and a cell lookup."""
    # The "map": previous endpoints binned into cells, each cell keeping the mean of its hits.
    pcell = np.floor(prev / resolution).astype(np.int64)
    lo = pcell.min(axis=0)
    dims = pcell.max(axis=0) - lo + 1
    n_cells = int(dims[0]) * int(dims[1])
    dense = n_cells <= _DENSE_CELLS
    if dense:
        # A dense cell table over the previous scan's bounding box: O(1) lookups.
        lin = (pcell[:, 0] - lo[0]) * dims[1] + (pcell[:, 1] - lo[1])
        keys, inv = np.unique(lin, return_inverse=True)
        table = np.full(n_cells, -1, dtype=np.int64)
        table[keys] = np.arange(len(keys))
    else:
        # Huge extents (long-range outdoor scans): sorted hash keys and binary search.
        keys, inv = np.unique(_cell_keys(pcell[:, 0], pcell[:, 1]), return_inverse=True)
    counts = np.bincount(inv, minlength=len(keys)).astype(np.float64)
    means = np.stack(
        [np.bincount(inv, prev[:, k], minlength=len(keys)) / counts for k in (0, 1)], axis=1
    )

    def lookup(cx: NDArray[np.int64], cy: NDArray[np.int64]) -> NDArray[np.int64]:
        """Index into ``means`` of each cell, -1 where it holds no previous endpoint."""
        if dense:
            rx, ry = cx - lo[0], cy - lo[1]
            inside = (rx >= 0) & (rx < dims[0]) & (ry >= 0) & (ry < dims[1])
            got = table[np.where(inside, rx * dims[1] + ry, 0)]
            return np.where(inside, got, -1)
        q = _cell_keys(cx, cy).reshape(-1)
        order = np.argsort(q)  # sorted queries make searchsorted several times faster
        pos = np.empty(q.size, dtype=np.int64)
        pos[order] = np.searchsorted(keys, q[order])
        pos = np.minimum(pos, len(keys) - 1)
        return np.where(keys[pos] == q, pos, -1).reshape(cx.shape)

    return means, lookup


def _gmapping_features_numpy(
    previous: LaserScan | ArrayLike,
    current: LaserScan | ArrayLike,
    pose: ArrayLike,
    *,
    sigma: float = 0.05,
    kernel_size: int = 1,
    resolution: float = 0.05,
    free_cell_ratio: float = _FREE_CELL_RATIO,
    max_range: float | None = None,
) -> dict[str, float]:
    """Vectorised numpy reference of `gmapping_features` (same arguments and result).

    The original implementation, kept to check the compiled kernel against (``tests``); about
    10x slower per 1440-beam pair.
    """
    prev, cur_local, p = _gmapping_inputs(
        previous, current, pose, sigma, kernel_size, resolution, max_range
    )
    n_cur = len(cur_local)
    if n_cur == 0 or len(prev) == 0:
        return dict(_GMAPPING_ZERO)
    c, s = math.cos(p[2]), math.sin(p[2])
    cur = cur_local @ np.array([[c, s], [-s, c]]) + p[:2]

    means, lookup = _previous_cells(prev, resolution)

    # Coordinates kept as separate x / y arrays: reductions over a trailing axis of length 2
    # are slow in numpy.
    cx0 = np.floor(cur[:, 0] / resolution).astype(np.int64)
    cy0 = np.floor(cur[:, 1] / resolution).astype(np.int64)
    # Free-space companion: the point free_cell_ratio cells back along the beam.
    rx, ry = cur[:, 0] - p[0], cur[:, 1] - p[1]
    rng = np.maximum(np.hypot(rx, ry), 1e-12)
    back = np.maximum(rng - resolution * free_cell_ratio, 0.0) / rng
    fx = np.floor((p[0] + rx * back) / resolution).astype(np.int64) - cx0
    fy = np.floor((p[1] + ry * back) / resolution).astype(np.int64) - cy0

    # All (2k+1)^2 window cells of all endpoints at once: (W, M).
    span = np.arange(-kernel_size, kernel_size + 1)
    ox = np.repeat(span, len(span))[:, None]
    oy = np.tile(span, len(span))[:, None]
    wx, wy = cx0 + ox, cy0 + oy
    cell_idx = lookup(wx, wy)
    ok = (cell_idx >= 0) & (lookup(wx + fx, wy + fy) < 0)
    safe = np.maximum(cell_idx, 0)
    d2 = (cur[:, 0] - means[safe, 0]) ** 2 + (cur[:, 1] - means[safe, 1]) ** 2
    best = np.where(ok, d2, np.inf).min(axis=0)
    found = np.isfinite(best)
    total = float(np.exp(-best[found] / sigma).sum())
    return {
        "gmapping_score": total,
        "gmapping_score_norm": total / n_cur,
        "gmapping_matched": float(found.mean()),
    }
