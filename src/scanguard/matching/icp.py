"""Public ICP entry points: the paper's point-to-point ICP and a point-to-line ICP."""

from __future__ import annotations

import logging
import math
import time
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

import scanguard.matching._core as _core
from scanguard.errors import MatchingError
from scanguard.io.base import MAX_COORDINATE
from scanguard.matching.config import ICPConfig
from scanguard.matching.result import CONVERGED, MAX_ITERATIONS, NO_INLIERS, MatchResult
from scanguard.scan import LaserScan

logger = logging.getLogger(__name__)

PointsLike = LaserScan | ArrayLike
Method = Literal["point_to_point", "point_to_line"]

_MIN_NORMAL_NEIGHBORS = 3


def as_points(points: PointsLike, name: str = "points") -> NDArray[np.float64]:
    """Points ``(M, 2)`` float64 from a `LaserScan` (valid beams) or an array-like.

    Non-finite rows are dropped (a NaN point can never be matched).

    Raises:
        MatchingError: The array does not have shape ``(M, 2)``, or a point lies beyond
            ``+-MAX_COORDINATE`` (1e6 m): the grid kernels index cells by coordinate, and
            such values overflow them.
    """
    if isinstance(points, LaserScan):
        arr = points.points(np.float64)
    else:
        arr = np.asarray(points, dtype=np.float64)
        if arr.size == 0:
            return np.zeros((0, 2), dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise MatchingError(f"{name}: expected points of shape (M, 2), got {arr.shape}")
    out: NDArray[np.float64] = np.ascontiguousarray(arr, dtype=np.float64)
    # one compiled pass in the common all-finite case (the numpy version costs ~30 us)
    if not _core.all_finite(out):
        finite = np.isfinite(out).all(axis=1)
        logger.debug("%s: dropping %d non-finite points", name, int((~finite).sum()))
        out = np.ascontiguousarray(out[finite])
    if out.size and float(np.abs(out).max()) > MAX_COORDINATE:
        raise MatchingError(
            f"{name}: points beyond +-{MAX_COORDINATE:.0e} m (largest |coordinate| "
            f"{float(np.abs(out).max()):.6g}); a scan never reaches that far"
        )
    return out


def initial_pose(initial: ArrayLike | None) -> NDArray[np.float64]:
    """The initial guess as 3 floats (None = identity), checked: every matcher's one rule.

    A non-finite guess is returned as it is (matchers report it as a failed match);
    a finite one must lie within ``+-MAX_COORDINATE`` (1e6 m) in x and y.

    Raises:
        MatchingError: Not 3 numbers, or a translation beyond the bound (such a guess is a
            caller's bug, and overflows the compiled kernels).
    """
    if initial is None:
        return np.zeros(3, dtype=np.float64)
    try:
        init = np.asarray(initial, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise MatchingError(
            f"initial guess must be a pose (x, y, theta), got {type(initial).__name__}"
        ) from None
    if init.shape != (3,):
        raise MatchingError(f"initial guess must be a pose (x, y, theta), got shape {init.shape}")
    with np.errstate(invalid="ignore"):
        far = bool((np.abs(init[:2]) > MAX_COORDINATE).any() and np.isfinite(init).all())
    if far:
        raise MatchingError(
            f"initial guess ({init[0]:.6g}, {init[1]:.6g}) beyond +-{MAX_COORDINATE:.0e} m"
        )
    return init.copy()


def _failed(
    reason: str,
    init: NDArray[np.float64],
    cfg: ICPConfig,
    t0: float,
    n_src: int,
    n_tgt: int,
    method: str,
    iterations: int = 0,
) -> MatchResult:
    logger.debug("%s: no match (%s)", method, reason)
    return MatchResult(
        pose=init.copy(),
        iterations=iterations,
        converged=False,
        reason=reason,
        mean_residual=float("nan"),
        median_residual=float("nan"),
        inlier_ratio=0.0,
        inlier_threshold=cfg.inlier_threshold,
        time_s=time.perf_counter() - t0,
        n_source=n_src,
        n_target=n_tgt,
        method=method,
    )


def match(
    method: Method,
    source: PointsLike,
    target: PointsLike,
    initial: ArrayLike | None = None,
    config: ICPConfig | None = None,
) -> MatchResult:
    """Run one ICP variant; see `icp_point_to_point` and `icp_point_to_line`.

    Bad data (too few valid points, non-finite initial guess, divergence) never raises: the
    result is flagged ``converged=False`` with a ``reason``.

    Raises:
        MatchingError: Unknown method or arrays of the wrong shape.
    """
    return match_starts(method, source, target, [initial], config)[0]


def match_starts(
    method: Method,
    source: PointsLike,
    target: PointsLike,
    initials: list[ArrayLike | None],
    config: ICPConfig | None = None,
) -> list[MatchResult]:
    """`match` from each of several initial guesses, the target's search structures built once.

    Each result is the one `match` gives from that guess alone (bit for bit); a second
    start against a large target skips building its grid, cover and normals (~0.4 ms of
    ~1.8 ms on a 10,000-point local map).

    Raises:
        MatchingError: Unknown method or arrays of the wrong shape.
    """
    t0 = time.perf_counter()
    cfg = config or ICPConfig()
    name = f"icp_{method}"
    if method not in ("point_to_point", "point_to_line"):
        raise MatchingError(f"unknown ICP method {method!r}")
    src = as_points(source, "source")
    tgt = as_points(target, "target")
    inits = [initial_pose(initial) for initial in initials]
    n_src, n_tgt = src.shape[0], tgt.shape[0]
    out: list[MatchResult | None] = [None] * len(inits)
    run: list[int] = []
    for s, init in enumerate(inits):
        if not all(math.isfinite(v) for v in init.tolist()):
            out[s] = _failed("non-finite initial guess", np.zeros(3), cfg, t0, n_src, n_tgt, name)
        elif n_src < cfg.min_points or n_tgt < cfg.min_points:
            reason = f"too few valid points (source {n_src}, target {n_tgt}; need {cfg.min_points})"
            out[s] = _failed(reason, init, cfg, t0, n_src, n_tgt, name)
        else:
            run.append(s)
    if run:
        max_d = cfg.max_correspondence_distance
        tuples = _core.run_match(
            method == "point_to_line",
            src,
            tgt,
            np.array([inits[s] for s in run]),
            cfg.cell_size,
            cfg.max_iterations,
            cfg.translation_tol,
            math.radians(cfg.rotation_tol_deg),
            cfg.stop_rule == "paper",
            math.inf if max_d is None else max_d * max_d,
            cfg.trim_fraction,
            cfg.huber_delta,
            cfg.normal_radius,
            _MIN_NORMAL_NEIGHBORS,
            cfg.inlier_threshold,
            cfg.threads,
        )
        for s, result in zip(run, tuples, strict=True):
            out[s] = _result(result, inits[s], cfg, t0, n_src, n_tgt, name)
    return [r for r in out if r is not None]


def _result(
    result: _core.MatchTuple,
    init: NDArray[np.float64],
    cfg: ICPConfig,
    t0: float,
    n_src: int,
    n_tgt: int,
    name: str,
) -> MatchResult:
    """The `MatchResult` of one compiled match."""
    x, y, th, iters, converged, status, mean_d, med, hess, eig, n_in = result
    if status == _core.STATUS_FEW_PAIRS:
        reason = "too few correspondences within the max correspondence distance"
        return _failed(reason, init, cfg, t0, n_src, n_tgt, name, iters)
    if status == _core.STATUS_DIVERGED:
        return _failed("estimate diverged (non-finite)", init, cfg, t0, n_src, n_tgt, name, iters)
    reason = CONVERGED if converged else MAX_ITERATIONS
    if converged and n_in == 0:
        # e.g. point-to-line started 1e5 m off: the lines slide, the steps shrink, and
        # nothing matches: a stop, not a match
        converged, reason = False, NO_INLIERS
    return MatchResult(
        pose=np.array([x, y, th], dtype=np.float64),
        iterations=int(iters),
        converged=bool(converged),
        reason=reason,
        mean_residual=float(mean_d),
        median_residual=float(med),
        inlier_ratio=n_in / n_src,
        inlier_threshold=cfg.inlier_threshold,
        hessian=hess,
        eigenvalues=eig,
        time_s=time.perf_counter() - t0,
        n_source=n_src,
        n_target=n_tgt,
        method=name,
        n_inliers=int(n_in),
    )


def icp_point_to_point(
    source: PointsLike,
    target: PointsLike,
    initial: ArrayLike | None = None,
    config: ICPConfig | None = None,
) -> MatchResult:
    """The paper's ICP (Jeong & Lee 2023, Sec. 2.2): align the current scan to the previous.

    Every iteration pairs each transformed source point with its nearest target point (true
    nearest neighbour; no distance limit unless ``config.max_correspondence_distance``), builds
    the centred cross-covariance, takes the SVD rotation ``R = U V^T`` (reflection fixed) and
    ``t = mu_Q - R mu_P``, and composes that update onto the estimate. It stops after
    ``config.max_iterations`` (20) or when the stop rule holds: ``ICPConfig.paper()`` stops when
    ``||t_update|| < 0.01 m`` (the paper's rule), the default config when the update is below
    1 mm and 0.01 deg.

    Args:
        source: Current scan (a `LaserScan` or ``(M, 2)`` points, sensor frame).
        target: Previous scan (same forms).
        initial: Initial guess of the source pose in the target frame (e.g. from odometry);
            None = identity, as in the paper.
        config: Settings; None = `ICPConfig()` (proper convergence).

    Returns:
        The `MatchResult` (pose of the current scan in the previous scan's frame).

    Raises:
        MatchingError: Arrays of the wrong shape (bad *data* never raises).
    """
    return match("point_to_point", source, target, initial, config)


def icp_point_to_line(
    source: PointsLike,
    target: PointsLike,
    initial: ArrayLike | None = None,
    config: ICPConfig | None = None,
) -> MatchResult:
    """Point-to-line ICP (Censi 2008 metric) with trimming and a Huber kernel.

    Same arguments, conventions and result as `icp_point_to_point`. Residuals are distances
    from transformed source points to the line through the nearest target point (normal by
    PCA of its neighbours within ``config.normal_radius``); the closest
    ``config.trim_fraction`` of pairs are kept and Huber-weighted (``config.huber_delta``);
    each iteration takes one Gauss-Newton step.

    Raises:
        MatchingError: Arrays of the wrong shape.
    """
    return match("point_to_line", source, target, initial, config)
