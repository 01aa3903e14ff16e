"""Classical scan-matching failure detectors, compared with the CNN in the same tables.

Every detector has the same small API (`Detector`): ``fit(features, labels, select=...)``
fits it on the training split and chooses its operating threshold on the selection set
``select`` (the validation split: pairs it was not fitted on), ``predict_proba(features)``
returns a score in ``[0, 1]`` where higher means "more likely a fault" (label 1),
``predict(features)`` returns 0/1, and ``threshold`` / ``name`` describe it. ``features`` is
either a mapping of named columns (the keys of `scanguard.matching.MatchResult.metrics` plus
``gmapping_score``) or a 2-D array.

The comparison with the CNN is meant to be fair, i.e. against what a careful user would
configure: every default detector reads only **scale-free** features (the same meaning for any
sensor and robot speed: `SCALE_FREE_METRICS_FEATURES`; raw counts, raw eigenvalues, the raw
GMapping score and the motion size are `SCALE_DEPENDENT_METRICS_FEATURES`), and every threshold
is chosen by the CNN's rule (`THRESHOLD_RULE`: maximum balanced accuracy on the selection set,
`scanguard.detect.calibrate.choose_threshold` for probabilities).

* `ThresholdDetector` — one quality metric and a direction (``"high"``: large values mean
  fault, e.g. the ICP residual; ``"low"``: small values mean fault, e.g. the inlier ratio, the
  smallest Hessian eigenvalue per inlier or the per-beam GMapping score). The threshold
  maximises the balanced accuracy (or the plain accuracy), so class imbalance does not push it
  to "everything is normal".
* `MetricsModelDetector` — gradient boosting (or logistic regression on standardised,
  log-compressed features) over the scale-free quality metrics together, its probability
  threshold chosen by `scanguard.detect.calibrate.choose_threshold`.
* `gmapping_score` — GMapping's ``ScanMatcher::score`` with the previous scan as the map.

`BASELINES` names the default set used in the evaluation table; `make_baseline` builds one,
`save_detector` / `load_detector` ship fitted ones (JSON; the sklearn model is pickled into the
JSON as base64, so only load files you trust).
"""

from __future__ import annotations

import base64
import json
import logging
import math
import pickle
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from scanguard.detect.odometry import ODOMETRY_FEATURES
from scanguard.errors import ConfigError, ModelError, ScanError
from scanguard.fsutil import atomic_write_text
from scanguard.scan import LaserScan

log = logging.getLogger(__name__)

__all__ = [
    "BASELINES",
    "DEFAULT_METRICS_FEATURES",
    "LEGACY_METRICS_FEATURES",
    "ODOMETRY_BASELINES",
    "SCALE_DEPENDENT_METRICS_FEATURES",
    "SCALE_FREE_METRICS_FEATURES",
    "THRESHOLD_RULE",
    "Detector",
    "FeaturesLike",
    "MetricsModelDetector",
    "ThresholdDetector",
    "balanced_accuracy",
    "gmapping_features",
    "gmapping_score",
    "load_detector",
    "make_baseline",
    "save_detector",
    "with_derived_features",
]

FeaturesLike = Mapping[str, ArrayLike] | ArrayLike
"""Named feature columns ``{name: (N,)}`` or an ``(N, K)`` array (``(N,)`` for one feature)."""

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


# --------------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------------

SCALE_FREE_METRICS_FEATURES: tuple[str, ...] = (
    "mean_residual",
    "median_residual",
    "inlier_ratio",
    "eig_min_per_inlier",
    "gmapping_score_norm",
    "condition_number",
    "iterations",
    "converged",
)
"""Quality metrics that mean the same for any sensor and robot speed.

The hybrid CNN's `scanguard.detect.model.METRIC_FEATURES` plus the (dimensionless) Hessian
``condition_number``: per-point residuals, fractions (inlier ratio, per-beam GMapping score),
the smallest eigenvalue per inlier, and the solver's iteration count and convergence flag.
"""

SCALE_DEPENDENT_METRICS_FEATURES: tuple[str, ...] = (
    "eig_min",
    "eig_mid",
    "eig_max",
    "n_source",
    "n_target",
    "n_inliers",
    "translation",
    "rotation",
    "gmapping_score",
)
"""Metrics whose values depend on the sensor (beam count) or the robot's step size.

Raw point counts, raw Hessian eigenvalues and the raw GMapping score grow with the number of
beams; ``translation`` / ``rotation`` with the speed. A model trained on them in simulation
rejects every pair of a 180-beam SICK log with ~1 m steps, so no default detector reads them.
"""

DEFAULT_METRICS_FEATURES: tuple[str, ...] = SCALE_FREE_METRICS_FEATURES
"""Quality metrics the metrics model uses when present (never errors or labels: no leakage).

Only scale-free ones (`SCALE_FREE_METRICS_FEATURES`), so a model fitted on simulated pairs
means the same on a real robot."""

LEGACY_METRICS_FEATURES: tuple[str, ...] = (
    "iterations",
    "converged",
    "mean_residual",
    "median_residual",
    "inlier_ratio",
    "eig_min",
    "eig_mid",
    "eig_max",
    "condition_number",
    "eig_min_per_inlier",
    "n_source",
    "n_target",
    "n_inliers",
    "translation",
    "rotation",
    "ok",
    "gmapping_score",
    "gmapping_score_norm",
)
"""Every stored quality metric: the metrics model's former default feature set.

Kept to reproduce old figures (``MetricsModelDetector(LEGACY_METRICS_FEATURES)``) and as the
list of ICP metrics a harvest stores. It includes `SCALE_DEPENDENT_METRICS_FEATURES`, so a
model on it does **not** transfer between sensors or robots (on real CARMEN logs the one fitted
on simulated pairs rejected every pair)."""


def with_derived_features(features: Mapping[str, ArrayLike]) -> dict[str, FloatArray]:
    """Add features that can be derived from stored ones, as float64 columns.

    * ``gmapping_score_norm = gmapping_score / n_source`` (the dataset stores only the raw sum;
      ``n_source`` is the number of current-scan points given to the matcher).
    * ``eig_min_per_inlier = eig_min / n_inliers``.

    Existing columns are never overwritten.
    """
    out = {k: np.asarray(v, dtype=np.float64) for k, v in features.items()}
    with np.errstate(divide="ignore", invalid="ignore"):
        if "gmapping_score_norm" not in out and {"gmapping_score", "n_source"} <= out.keys():
            n = out["n_source"]
            out["gmapping_score_norm"] = np.where(n > 0, out["gmapping_score"] / n, 0.0)
        if "eig_min_per_inlier" not in out and {"eig_min", "n_inliers"} <= out.keys():
            n = out["n_inliers"]
            out["eig_min_per_inlier"] = np.where(n > 0, out["eig_min"] / n, 0.0)
    return out


def _columns(features: FeaturesLike, names: Sequence[str] | None, who: str) -> FloatArray:
    """``(N, K)`` float64 matrix of the named columns (or of a raw array)."""
    if isinstance(features, Mapping):
        if names is None:
            raise ModelError(f"{who}: feature names are needed to read a feature mapping")
        cols = with_derived_features(features)
        missing = [n for n in names if n not in cols]
        if missing:
            raise ModelError(f"{who}: missing feature(s) {missing}; available: {sorted(cols)}")
        arr = np.stack([cols[n].reshape(-1) for n in names], axis=1) if names else None
        if arr is None:
            raise ModelError(f"{who}: no features selected")
        return arr
    arr = np.asarray(features, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ModelError(f"{who}: features must be a mapping or a 1-D/2-D array, got {arr.shape}")
    if names is not None and arr.shape[1] != len(names):
        raise ModelError(
            f"{who}: expected {len(names)} feature column(s) {list(names)}, got {arr.shape[1]}"
        )
    return arr


def _labels(labels: ArrayLike, n: int, who: str) -> NDArray[np.int64]:
    y = np.asarray(labels).reshape(-1)
    if len(y) != n:
        raise ModelError(f"{who}: {n} feature rows but {len(y)} labels")
    if not np.isin(y, (-1, 0, 1)).all():
        raise ModelError(f"{who}: labels must be 0 (normal), 1 (fault) or -1 (ambiguous)")
    return y.astype(np.int64)


def _check_two_classes(y: NDArray[np.int64], who: str) -> None:
    if not ((y == 0).any() and (y == 1).any()):
        raise ModelError(
            f"{who}: training needs both normal (0) and fault (1) labels; got "
            f"{int((y == 0).sum())} normal and {int((y == 1).sum())} fault"
        )


# --------------------------------------------------------------------------------------------
# Detectors
# --------------------------------------------------------------------------------------------


@runtime_checkable
class Detector(Protocol):
    """The common API of every baseline detector."""

    name: str

    @property
    def threshold(self) -> float:
        """Decision threshold (feature units for `ThresholdDetector`, probability otherwise)."""
        ...

    def fit(
        self,
        features: FeaturesLike,
        labels: ArrayLike,
        *,
        select: tuple[FeaturesLike, ArrayLike] | None = None,
    ) -> Detector:
        """Tune on training data (labels -1 are ignored), threshold on ``select``; returns self."""
        ...

    def select_threshold(self, features: FeaturesLike, labels: ArrayLike) -> float:
        """Choose the operating threshold on labelled pairs by `THRESHOLD_RULE`; returns it."""
        ...

    def predict_proba(self, features: FeaturesLike) -> FloatArray:
        """``(N,)`` fault scores in ``[0, 1]``; higher = more likely a fault."""
        ...

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """``(N,)`` 0 = normal, 1 = fault."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state of the fitted detector."""
        ...


Criterion = Literal["balanced_accuracy", "accuracy"]
Selection = tuple[FeaturesLike, ArrayLike]
"""A selection set: features and labels of pairs the detector is not fitted on."""

THRESHOLD_RULE = "max balanced accuracy on the selection split"
"""How every detector's operating threshold is chosen: the CNN's rule
(`scanguard.detect.calibrate.choose_threshold`), on pairs not used to fit the detector."""


def balanced_accuracy(pred: ArrayLike, labels: ArrayLike) -> float:
    """Mean of the fault recall and the normal recall of 0/1 predictions (labels -1 ignored).

    NaN when a class is missing.
    """
    p = np.asarray(pred).reshape(-1)
    y = np.asarray(labels).reshape(-1)
    pos, neg = y == 1, y == 0
    if not pos.any() or not neg.any():
        return math.nan
    return 0.5 * (float(np.mean(p[pos] == 1)) + float(np.mean(p[neg] == 0)))


def _best_threshold(
    score: FloatArray, y: NDArray[np.int64], criterion: Criterion
) -> tuple[float, float]:
    """Threshold ``t`` on an oriented score (fault iff ``score > t``) maximising ``criterion``.

    Candidates are midpoints between consecutive distinct finite scores plus one below and one
    above all of them; among equally good candidates the middle one is taken, so a clean gap
    between the classes gets its centre. Returns ``(t, criterion value)``.
    """
    pos = np.sort(score[y == 1])
    neg = np.sort(score[y == 0])
    finite = np.unique(score[np.isfinite(score)])
    if len(finite) == 0:
        cand = np.array([0.0])
    else:
        mids = (finite[:-1] + finite[1:]) / 2.0
        cand = np.concatenate([[finite[0] - 1.0], mids, [finite[-1] + 1.0]])
    tp = len(pos) - np.searchsorted(pos, cand, side="right")
    tn = np.searchsorted(neg, cand, side="right")
    if criterion == "balanced_accuracy":
        value = 0.5 * (tp / len(pos) + tn / len(neg))
    else:
        value = (tp + tn) / (len(pos) + len(neg))
    best = np.flatnonzero(value >= value.max() - 1e-12)
    i = int(best[len(best) // 2])
    return float(cand[i]), float(value[i])


class ThresholdDetector:
    """Fault iff one quality metric is above (``"high"``) or below (``"low"``) a threshold.

    The threshold maximises the balanced accuracy (default) or the accuracy on the selection
    set given to `fit` (``select``, pairs it is not fitted on: the CNN's rule, see
    `THRESHOLD_RULE`), else on the fitting data; among equally good thresholds the middle one
    is taken (for a monotone score this is `scanguard.detect.calibrate.choose_threshold` with
    its ties resolved to the centre of the tied range). Non-finite feature values (a failed
    match has NaN residuals) count as faults.
    `predict_proba` is a strictly monotone squashing of the raw feature (``0.5`` at the
    threshold), not a calibrated probability: its ROC curve equals that of the raw feature
    (`score` returns the raw feature in fault-positive orientation).

    Args:
        feature: Feature name (a key of ``MatchResult.metrics()``, ``gmapping_score``, ...).
        direction: ``"high"`` if large values mean fault, ``"low"`` if small values do.
        name: Display name (defaults to ``feature``).
        criterion: ``"balanced_accuracy"`` or ``"accuracy"``.
    """

    def __init__(
        self,
        feature: str,
        direction: Literal["high", "low"],
        *,
        name: str | None = None,
        criterion: Criterion = "balanced_accuracy",
    ) -> None:
        if direction not in ("high", "low"):
            raise ConfigError(f"ThresholdDetector({feature}): direction must be 'high' or 'low'")
        if criterion not in ("balanced_accuracy", "accuracy"):
            raise ConfigError(f"ThresholdDetector({feature}): unknown criterion {criterion!r}")
        self.feature = feature
        self.direction: Literal["high", "low"] = direction
        self.name = name or feature
        self.criterion: Criterion = criterion
        self._t: float | None = None  # threshold on the oriented score
        self.scale = 1.0
        self.train_score: float | None = None
        self.select_score: float | None = None
        self.n_select = 0

    @property
    def fitted(self) -> bool:
        """Whether `fit` (or `load_detector`) has set the threshold."""
        return self._t is not None

    @property
    def threshold(self) -> float:
        """The threshold in the feature's own units (NaN until fitted)."""
        if self._t is None:
            return math.nan
        return self._t if self.direction == "high" else -self._t

    def _oriented_threshold(self) -> float:
        if self._t is None:
            raise ModelError(f"detector {self.name!r} is not fitted")
        return self._t

    def score(self, features: FeaturesLike) -> FloatArray:
        """Raw feature in fault-positive orientation (``-x`` for ``"low"``); NaN -> +inf."""
        x = _columns(features, [self.feature], f"detector {self.name!r}")[:, 0]
        s = x if self.direction == "high" else -x
        return np.where(np.isnan(s), np.inf, s)

    def _labelled_scores(
        self, features: FeaturesLike, labels: ArrayLike, what: str = ""
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """Oriented scores and labels of the labelled (0/1) rows; both classes required."""
        who = f"detector {self.name!r}{what}"
        s = self.score(features)
        y = _labels(labels, len(s), who)
        keep = y >= 0
        _check_two_classes(y[keep], who)
        return s[keep], y[keep]

    def _criterion(self, s: FloatArray, y: NDArray[np.int64]) -> float:
        pred = (s > self._oriented_threshold()).astype(np.int64)
        if self.criterion == "balanced_accuracy":
            return balanced_accuracy(pred, y)
        return float(np.mean(pred == y))

    def select_threshold(self, features: FeaturesLike, labels: ArrayLike) -> float:
        """Choose the threshold on labelled pairs (labels -1 ignored) and return it.

        The rule of `THRESHOLD_RULE`; ``select_score`` is the criterion value reached.
        """
        s, y = self._labelled_scores(features, labels, " (selection set)")
        self._t, self.select_score = _best_threshold(s, y, self.criterion)
        self.n_select = len(y)
        return self.threshold

    def fit(
        self,
        features: FeaturesLike,
        labels: ArrayLike,
        *,
        select: Selection | None = None,
    ) -> ThresholdDetector:
        """Fit on training data (labels -1 are ignored); the threshold on ``select`` if given.

        Args:
            features: Feature columns of the fitting pairs.
            labels: Their labels.
            select: ``(features, labels)`` of pairs not used for fitting (the validation split)
                on which `select_threshold` chooses the threshold; None = the fitting pairs.
        """
        s, y = self._labelled_scores(features, labels)
        if select is None:
            self.select_threshold(features, labels)
        else:
            self.select_threshold(*select)
        self.train_score = self._criterion(s, y)
        fin = s[np.isfinite(s)]
        if len(fin) >= 2:
            q75, q25 = np.percentile(fin, [75, 25])
            spread = (q75 - q25) / 1.349 or float(np.std(fin))
        else:
            spread = 0.0
        self.scale = float(spread) if spread > 0 else 1.0
        log.debug(
            "%s: threshold %s %.6g (%s %.4f on %d selection pairs, %.4f on %d fitting pairs)",
            self.name,
            ">" if self.direction == "high" else "<",
            self.threshold,
            self.criterion,
            self.select_score,
            self.n_select,
            self.train_score,
            len(y),
        )
        return self

    def predict_proba(self, features: FeaturesLike) -> FloatArray:
        """Monotone fault score in ``(0, 1)`` (``> 0.5`` iff past the threshold; inf -> 1)."""
        t = self._oriented_threshold()
        s = self.score(features)
        with np.errstate(invalid="ignore", over="ignore"):
            z = (s - t) / self.scale
        # arctan, unlike a logistic, does not saturate to exactly 0/1 for large |z|, so the
        # ranking (and the ROC curve) of the raw feature is preserved.
        return np.asarray(0.5 + np.arctan(z) / np.pi, dtype=np.float64)

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """0 = normal, 1 = fault."""
        t = self._oriented_threshold()
        return (self.score(features) > t).astype(np.int64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state."""
        return {
            "type": "threshold",
            "name": self.name,
            "feature": self.feature,
            "direction": self.direction,
            "criterion": self.criterion,
            "threshold": None if self._t is None else self.threshold,
            "scale": self.scale,
            "train_score": self.train_score,
            "select_score": self.select_score,
            "n_select": self.n_select,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ThresholdDetector:
        """Rebuild from `to_dict` output."""
        det = cls(
            data["feature"], data["direction"], name=data["name"], criterion=data["criterion"]
        )
        thr = data.get("threshold")
        if thr is not None:
            det._t = float(thr) if det.direction == "high" else -float(thr)
        det.scale = float(data.get("scale", 1.0))
        det.train_score = data.get("train_score")
        det.select_score = data.get("select_score")
        det.n_select = int(data.get("n_select") or 0)
        return det

    def __repr__(self) -> str:
        thr = f"{self.threshold:.6g}" if self.fitted else "unfitted"
        op = ">" if self.direction == "high" else "<"
        return f"ThresholdDetector({self.name!r}: fault if {self.feature} {op} {thr})"


_THREADPOOLS: Any = None


def _single_thread() -> Any:
    """Limit OpenMP/BLAS to one thread while fitting or predicting.

    The models are tiny and machines are often shared, so threads cost more than they save.
    """
    global _THREADPOOLS
    if _THREADPOOLS is None:
        from threadpoolctl import ThreadpoolController

        # Scanning the loaded libraries (what `threadpool_limits` does on every call) costs
        # ~4 ms, more than a one-pair prediction; the pools are those of numpy/scipy/sklearn,
        # all loaded by the time a model is fitted or unpickled.
        _THREADPOOLS = ThreadpoolController()
    return _THREADPOOLS.limit(limits=1)


class MetricsModelDetector:
    """A small classifier over all ICP quality metrics together.

    ``kind="gbm"`` (default) is sklearn's ``HistGradientBoostingClassifier`` (shallow trees,
    fixed seed, no early stopping, NaN handled natively); ``kind="logistic"`` is a logistic
    regression on standardised features after a signed ``log1p`` compression (condition numbers
    span many decades) with NaN imputed by the training median. Both weight the classes
    "balanced". ``+-inf`` values become NaN.

    The model is fitted on the fitting pairs; its probability threshold is then chosen by the
    CNN's rule, `scanguard.detect.calibrate.choose_threshold` (max balanced accuracy, ties ->
    nearest 0.5), on the selection set given to `fit` (pairs the model was not fitted on), else
    on the fitting pairs. A pair is a fault when its probability is ``>= threshold``.

    Args:
        features: Feature names to use; None = those of `DEFAULT_METRICS_FEATURES` (scale-free
            only) present, with a finite value, at fit time (with a mapping) or every column
            (with an array). Pass
            `LEGACY_METRICS_FEATURES` to reproduce the former, non-transferring model.
        kind: ``"gbm"`` or ``"logistic"``.
        name: Display name.
        random_state: Seed of the gradient boosting.
    """

    def __init__(
        self,
        features: Sequence[str] | None = None,
        *,
        kind: Literal["gbm", "logistic"] = "gbm",
        name: str = "metrics-model",
        random_state: int = 0,
    ) -> None:
        if kind not in ("gbm", "logistic"):
            raise ConfigError(
                f"MetricsModelDetector: kind must be 'gbm' or 'logistic', not {kind!r}"
            )
        self.features: list[str] | None = None if features is None else list(features)
        self.kind: Literal["gbm", "logistic"] = kind
        self.name = name
        self.random_state = random_state
        self._threshold = 0.5
        self.model: Any = None
        self.select_score: float | None = None
        self.n_select = 0

    @property
    def threshold(self) -> float:
        """Probability threshold of `predict`."""
        return self._threshold

    @threshold.setter
    def threshold(self, value: float) -> None:
        self._threshold = float(value)

    def _matrix(self, features: FeaturesLike) -> FloatArray:
        x = _columns(features, self.features, f"detector {self.name!r}")
        x = np.where(np.isfinite(x), x, np.nan)
        if self.kind == "logistic":
            x = np.sign(x) * np.log1p(np.abs(x))
        return x

    def _build(self) -> Any:
        if self.kind == "gbm":
            from sklearn.ensemble import HistGradientBoostingClassifier

            return HistGradientBoostingClassifier(
                max_iter=100,
                learning_rate=0.1,
                max_leaf_nodes=15,
                l2_regularization=1.0,
                class_weight="balanced",
                early_stopping=False,
                random_state=self.random_state,
            )
        from sklearn.impute import SimpleImputer
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        return make_pipeline(
            SimpleImputer(strategy="median", keep_empty_features=True),
            StandardScaler(),
            LogisticRegression(class_weight="balanced", max_iter=2000),
        )

    def select_threshold(self, features: FeaturesLike, labels: ArrayLike) -> float:
        """Choose the probability threshold on labelled pairs (labels -1 ignored); return it.

        `scanguard.detect.calibrate.choose_threshold` on the model's fault probabilities, the
        rule of the CNN's operating threshold; ``select_score`` is the balanced accuracy there.

        Raises:
            ModelError: Not fitted, or the pairs lack a class.
        """
        from scanguard.detect.calibrate import choose_threshold

        who = f"detector {self.name!r} (selection set)"
        proba = self.predict_proba(features)
        y = _labels(labels, len(proba), who)
        keep = y >= 0
        _check_two_classes(y[keep], who)
        self._threshold = choose_threshold(y[keep], proba[keep])
        self.select_score = balanced_accuracy(proba[keep] >= self._threshold, y[keep])
        self.n_select = int(keep.sum())
        return self._threshold

    def fit(
        self,
        features: FeaturesLike,
        labels: ArrayLike,
        *,
        select: Selection | None = None,
    ) -> MetricsModelDetector:
        """Train on the fitting pairs (labels -1 are ignored); the threshold on ``select``.

        Args:
            features: Feature columns of the fitting pairs (the training split).
            labels: Their labels.
            select: ``(features, labels)`` of pairs not used for fitting (the validation split)
                on which `select_threshold` chooses the threshold; None = the fitting pairs.
        """
        who = f"detector {self.name!r}"
        if self.features is None:
            if isinstance(features, Mapping):
                available = with_derived_features(features)
                # a metric the matcher never fills (all NaN) carries nothing, and breaks the
                # gradient boosting's binning
                self.features = [
                    f
                    for f in DEFAULT_METRICS_FEATURES
                    if f in available and np.isfinite(available[f]).any()
                ]
            else:
                arr = np.asarray(features)
                ncol = 1 if arr.ndim == 1 else arr.shape[1]
                self.features = [f"f{i}" for i in range(ncol)]
            if not self.features:
                raise ModelError(f"{who}: none of {list(DEFAULT_METRICS_FEATURES)} is available")
        x = self._matrix(features)
        y = _labels(labels, len(x), who)
        keep = y >= 0
        x, y = x[keep], y[keep]
        _check_two_classes(y, who)
        with _single_thread():
            self.model = self._build().fit(x, y)
        if select is None:
            self.select_threshold(features, labels)
        else:
            self.select_threshold(*select)
        log.debug(
            "%s: %s on %d pairs, features %s, threshold %.4g (balanced accuracy %.4f on %d "
            "selection pairs)",
            self.name,
            self.kind,
            len(y),
            self.features,
            self._threshold,
            self.select_score,
            self.n_select,
        )
        return self

    def predict_proba(self, features: FeaturesLike) -> FloatArray:
        """Fault probability ``(N,)``."""
        if self.model is None:
            raise ModelError(f"detector {self.name!r} is not fitted")
        with _single_thread():
            proba = self.model.predict_proba(self._matrix(features))[:, 1]
        return np.asarray(proba, dtype=np.float64)

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """0 = normal, 1 = fault (probability >= `threshold`)."""
        return (self.predict_proba(features) >= self._threshold).astype(np.int64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state (the sklearn model pickled as base64)."""
        import sklearn

        return {
            "type": "metrics-model",
            "name": self.name,
            "kind": self.kind,
            "features": self.features,
            "threshold": self._threshold,
            "threshold_rule": THRESHOLD_RULE,
            "select_score": self.select_score,
            "n_select": self.n_select,
            "random_state": self.random_state,
            "sklearn_version": sklearn.__version__,
            "model_pickle": None
            if self.model is None
            else base64.b64encode(pickle.dumps(self.model, protocol=4)).decode("ascii"),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MetricsModelDetector:
        """Rebuild from `to_dict` output (unpickles the model: trusted files only)."""
        det = cls(
            data["features"],
            kind=data["kind"],
            name=data["name"],
            random_state=int(data.get("random_state", 0)),
        )
        det.threshold = float(data.get("threshold", 0.5))
        det.select_score = data.get("select_score")
        det.n_select = int(data.get("n_select") or 0)
        blob = data.get("model_pickle")
        if blob is not None:
            det.model = pickle.loads(base64.b64decode(blob))
        return det

    def __repr__(self) -> str:
        state = "fitted" if self.model is not None else "unfitted"
        return f"MetricsModelDetector({self.name!r}, {self.kind}, {state})"


# --------------------------------------------------------------------------------------------
# Registry and persistence
# --------------------------------------------------------------------------------------------

# Every feature read here is in SCALE_FREE_METRICS_FEATURES (checked by the tests): a baseline
# fitted on simulated pairs means the same on a real robot.
BASELINES: dict[str, Callable[[], Detector]] = {
    "residual": lambda: ThresholdDetector("mean_residual", "high", name="residual"),
    "overlap": lambda: ThresholdDetector("inlier_ratio", "low", name="overlap"),
    # Per inlier: the raw eigenvalue grows with the number of matched points, which differs
    # between sensors; the plain ``eig_min`` is available as ThresholdDetector("eig_min", "low").
    "degeneracy": lambda: ThresholdDetector("eig_min_per_inlier", "low", name="degeneracy"),
    # Per beam: the raw GMapping score grows with the number of beams.
    "gmapping": lambda: ThresholdDetector("gmapping_score_norm", "low", name="gmapping"),
    "metrics-model": lambda: MetricsModelDetector(name="metrics-model"),
}
"""Default baselines of the evaluation table: name -> factory of an unfitted detector.

All read only scale-free features (`SCALE_FREE_METRICS_FEATURES`) and choose their threshold
by `THRESHOLD_RULE` when fitted with a selection set."""

ODOMETRY_BASELINES: dict[str, Callable[[], Detector]] = {
    # the chi-like test a careful user with wheel odometry writes first: the larger of the
    # translational and rotational disagreement, in standard deviations of the noise model
    "odometry": lambda: ThresholdDetector("odom_max_z", "high", name="odometry"),
    "metrics+odometry": lambda: MetricsModelDetector(
        [*SCALE_FREE_METRICS_FEATURES, *ODOMETRY_FEATURES], name="metrics+odometry"
    ),
}
"""Classical detectors that also read the odometry disagreement (`scanguard.detect.odometry`).

They need the odometry features of a pair store (`scanguard.detect.evaluate.store_features`),
so they take part in evaluations, not in ``run``'s baseline instance; on pairs without
odometry the features are 0 and the mask says so."""


def make_baseline(name: str) -> Detector:
    """A new, unfitted baseline from `BASELINES` or `ODOMETRY_BASELINES`.

    Raises:
        ConfigError: Unknown name (the message lists the known ones).
    """
    known = {**BASELINES, **ODOMETRY_BASELINES}
    try:
        return known[name]()
    except KeyError:
        raise ConfigError(f"unknown baseline {name!r}; known: {', '.join(sorted(known))}") from None


def save_detector(detector: Detector, path: str | Path) -> Path:
    """Write a (fitted) detector as JSON, atomically."""
    p = Path(path)
    atomic_write_text(p, json.dumps(detector.to_dict(), indent=1))
    return p


def load_detector(path: str | Path) -> Detector:
    """Load a detector written by `save_detector`.

    Raises:
        ModelError: Missing, not JSON, or not a detector file.
    """
    p = Path(path)
    if not p.is_file():
        raise ModelError(f"{p}: detector file not found")
    try:
        data = json.loads(p.read_text())
        kind = data["type"]
        if kind == "threshold":
            return ThresholdDetector.from_dict(data)
        if kind == "metrics-model":
            return MetricsModelDetector.from_dict(data)
    except (ValueError, KeyError, TypeError, pickle.UnpicklingError) as exc:
        raise ModelError(f"{p}: not a valid detector file ({exc})") from None
    raise ModelError(f"{p}: unknown detector type {kind!r}")
