"""Correlative scan-to-map matching (Olson 2009; Cartographer's fast correlative matcher).

The map is a `scanguard.matching.likelihood.LikelihoodGrid` (a smeared lookup table of map
points with its max-pooled pyramid for branch-and-bound). `correlative_match` finds the pose
(on the grid's lattice: whole cells in x and y, a fixed angular step) that maximises the mean
table value of the transformed source points over a search window, exactly, and a covariance
from the response surface around it. `match_to_map` adds a point-to-line ICP refinement and
returns a `MatchResult` like the project's other matchers. See ``docs/matching.md``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

import scanguard.matching._core as _core
import scanguard.matching._correlative as _k
import scanguard.matching.lanes as lanes
from scanguard.errors import ConfigError, MatchingError
from scanguard.geometry import wrap_angle
from scanguard.matching.config import CorrelativeConfig, ICPConfig
from scanguard.matching.icp import PointsLike, as_points, icp_point_to_line, initial_pose
from scanguard.matching.likelihood import CUTOFF_SIGMAS, LikelihoodGrid, pose_array, source_array
from scanguard.matching.result import CONVERGED, NO_INLIERS, MatchResult

logger = logging.getLogger(__name__)

#: Temperature of the covariance weights, relative to the best mean response: a pose whose
#: response is ``COVARIANCE_TAU * best`` below the best gets weight ``1/e``. Near the peak the
#: response falls like ``f delta^2 / (2 sigma^2)`` (``f``: share of points constrained along
#: ``delta``), so the weights are a Gaussian of std ``sigma sqrt(tau / f)``: about 1-1.5 cm
#: for the default sigma in a well-constrained room.
COVARIANCE_TAU = 0.05
#: The ICP refinement is kept when it moves the pose by at most this many cells and angular
#: steps. Two steps, not one: the best lattice pose itself can be ~1.2 steps off in theta
#: (points snap to cell centres, which trades rotation against translation).
REFINE_MAX_CELLS = 2.0
REFINE_MAX_STEPS = 2.0
_MIN_REFINE_POINTS = 5


@dataclass(frozen=True, eq=False)
class CorrelativeResult:
    """Outcome of `correlative_match`.

    Attributes:
        pose: ``(x, y, theta)`` of the source frame in the map frame (on the search lattice).
        score: Mean response at ``pose``, 0..1.
        covariance: 3x3 covariance of ``(x, y, theta)`` from the response surface (always
            positive definite).
        found: ``score >= min_score``. When False, ``pose`` is the initial pose, ``score`` its
            response and ``covariance`` that of a uniform distribution over the window.
        n_evaluated: Poses scored by the search (all levels; not the covariance's).
        time_s: Wall-clock time (s).
        theta_step: The angular step used (rad).
        n_source: Source points used.
    """

    pose: NDArray[np.float64]
    score: float
    covariance: NDArray[np.float64]
    found: bool
    n_evaluated: int
    time_s: float
    theta_step: float = 0.0
    n_source: int = 0


def _window(value: float | None, default: float, name: str) -> float:
    v = default if value is None else float(value)
    if not (math.isfinite(v) and v >= 0):
        raise MatchingError(f"{name} must be finite and >= 0, got {value}")
    return v


def _resolve_config(config: CorrelativeConfig | None, grid: LikelihoodGrid) -> CorrelativeConfig:
    cfg = grid.config if config is None else config
    if cfg is not grid.config:
        g = grid.config
        if not math.isclose(cfg.resolution, g.resolution) or not math.isclose(cfg.sigma, g.sigma):
            raise ConfigError(
                f"config (resolution {cfg.resolution}, sigma {cfg.sigma}) does not match the "
                f"grid's (resolution {g.resolution}, sigma {g.sigma}); build the grid with it"
            )
        if cfg.levels > grid.levels:
            raise ConfigError(
                f"config asks for {cfg.levels} levels, the grid was built with {grid.levels}"
            )
    return cfg


def theta_step_for(points: NDArray[np.float64], resolution: float) -> float:
    """Cartographer's angular step: the farthest point moves by at most ``resolution``."""
    d_max = float(np.sqrt(np.max(points[:, 0] ** 2 + points[:, 1] ** 2)))
    d_max = max(d_max, resolution)
    return math.acos(1.0 - resolution * resolution / (2.0 * d_max * d_max))


def _theta_offsets(window: float, step: float) -> tuple[NDArray[np.float64], float]:
    n = math.ceil(window / step - 1e-9)
    if (2 * n + 1) * step >= 2.0 * math.pi:
        # the whole circle: an even spacing without the duplicate at +-pi
        total = math.ceil(2.0 * math.pi / step)
        step = 2.0 * math.pi / total
        return (np.arange(total, dtype=np.float64) - total // 2) * step, step
    return np.arange(-n, n + 1, dtype=np.float64) * step, step


def correlative_match(
    source_points: PointsLike,
    grid: LikelihoodGrid,
    initial: ArrayLike,
    config: CorrelativeConfig | None = None,
    *,
    window_xy: float | None = None,
    window_theta: float | None = None,
    exclude: tuple[float, float, float] | None = None,
) -> CorrelativeResult:
    """Exhaustive correlative search of the window around ``initial``, by branch-and-bound.

    Poses are ``initial + (dx r, dy r, k step)`` for whole ``|dx|, |dy| <= ceil(window_xy /
    r)`` and ``|k| <= ceil(window_theta / step)``; the returned pose maximises the mean table
    value over all of them (ties: any one), the coarse levels being exact upper bounds.

    Args:
        source_points: Scan points ``(M, 2)`` in the sensor frame (or a `LaserScan`).
        grid: The map's likelihood grid.
        initial: Initial pose ``(x, y, theta)`` of the sensor in the map frame.
        config: Search settings; None = ``grid.config``. Its resolution and sigma must be the
            grid's; ``levels`` may be fewer than the grid's.
        window_xy: Overrides ``config.window_xy`` (m).
        window_theta: Overrides ``config.window_theta`` (rad).
        exclude: ``(x, y, radius)`` in the map frame: leave out every pose whose position
            lies within ``radius`` of ``(x, y)`` (at any angle), to find the best pose
            elsewhere (`second_peak`).

    Returns:
        The `CorrelativeResult`.

    Raises:
        MatchingError: No finite source point, a non-finite or malformed initial pose, a
            negative window.
        ConfigError: A config that does not fit the grid.
    """
    t0 = time.perf_counter()
    cfg = _resolve_config(config, grid)
    src = source_array(source_points, cfg.max_range)
    init = pose_array(initial, "initial pose")
    wxy = _window(window_xy, cfg.window_xy, "window_xy")
    wth = _window(window_theta, cfg.window_theta, "window_theta")
    r = grid.resolution
    n = src.shape[0]
    step0 = cfg.theta_step if cfg.theta_step is not None else theta_step_for(src, r)
    offsets, step = _theta_offsets(wth, step0)
    w = math.ceil(wxy / r - 1e-9)
    x0, y0 = grid.origin
    stack = grid.stack
    runs = _k.discretise_runs(src, init[0], init[1], init[2], offsets, x0, y0, r)
    threshold = cfg.min_score * n - 1e-9
    ex_dx = ex_dy = 0
    ex_r2 = -1.0
    if exclude is not None:
        ex_dx = round((exclude[0] - init[0]) / r)
        ex_dy = round((exclude[1] - init[1]) / r)
        ex_r2 = (max(exclude[2], 0.0) / r) ** 2
    k, dx, dy, best, n_eval, found = lanes.branch_and_bound(
        stack, grid.pad, runs, w, int(cfg.levels), threshold, (ex_dx, ex_dy, ex_r2)
    )
    if not found:
        s0 = grid.score(src, init)
        cov = np.diag([wxy**2 / 3 + r * r / 12, wxy**2 / 3 + r * r / 12, wth**2 / 3 + step**2 / 12])
        logger.debug("correlative: nothing above min_score %.3f (score at initial %.3f)",
                     cfg.min_score, s0)  # fmt: skip
        return CorrelativeResult(
            init.copy(), s0, cov, False, int(n_eval), time.perf_counter() - t0, step, n
        )
    th_off = float(offsets[k])
    pose = np.array([init[0] + dx * r, init[1] + dy * r, float(wrap_angle(init[2] + th_off))])
    cov = _covariance(grid, src, init, th_off, dx, dy, step, float(best) / n)
    score = float(best) / n
    return CorrelativeResult(
        pose, score, cov, score >= cfg.min_score, int(n_eval), time.perf_counter() - t0, step,
        n,
    )  # fmt: skip


def second_peak(
    source_points: PointsLike,
    grid: LikelihoodGrid,
    initial: ArrayLike,
    best: CorrelativeResult,
    config: CorrelativeConfig | None = None,
    *,
    radius: float,
    min_ratio: float,
) -> CorrelativeResult:
    """The best pose of the same search at least ``radius`` from ``best`` (an alias).

    A match in a corridor of evenly spaced doors, or between two alike rooms, has a second
    peak of almost the best response one period away; how close it comes is how ambiguous
    the match is. Only poses scoring at least ``min_ratio`` times ``best.score`` are looked
    for, which lets branch-and-bound prune the rest (``found`` is False when none does).

    Args:
        source_points: The points of the search that gave ``best``.
        grid: Its likelihood grid.
        initial: Its initial pose.
        best: Its result.
        config: Its settings (None: ``grid.config``).
        radius: Positions within this distance (m) of ``best.pose`` are left out.
        min_ratio: The smallest response, relative to the best, worth finding.

    Returns:
        The `CorrelativeResult` of the best pose elsewhere.
    """
    cfg = _resolve_config(config, grid).model_copy(
        update={"min_score": max(min_ratio * best.score, 1e-9)}
    )
    x, y = float(best.pose[0]), float(best.pose[1])
    return correlative_match(source_points, grid, initial, cfg, exclude=(x, y, radius))


def _covariance(
    grid: LikelihoodGrid,
    src: NDArray[np.float64],
    init: NDArray[np.float64],
    th_off: float,
    dx: int,
    dy: int,
    step: float,
    best: float,
) -> NDArray[np.float64]:
    """Weighted covariance of the finest responses around the best pose (Olson 2009, Karto).

    The neighbourhood spans ``h = max(3, ceil(2 sigma / r))`` cells (at most 10) each way in x
    and y and ``h`` angular steps in theta (a step moves the farthest point by one cell), so
    it covers the response peak's width, which the smearing sets. Weights are
    ``exp((s - s_best) / (COVARIANCE_TAU s_best))``. The quantisation variance of the lattice
    (``r^2 / 12``, ``step^2 / 12``) is added to the diagonal, which keeps the matrix positive
    definite even where the surface is sharp.
    """
    r = grid.resolution
    half = min(10, max(3, math.ceil(2.0 * grid.config.sigma / r)))
    rel = np.arange(-half, half + 1, dtype=np.float64) * step
    x0, y0 = grid.origin
    runs = _k.discretise_runs(src, init[0], init[1], init[2], th_off + rel, x0, y0, r)
    sums = _k.neighbourhood(grid.stack, grid.pad, *runs, dx, dy, half)
    s = sums / src.shape[0]
    ref = max(best, float(s.max()))
    tau = COVARIANCE_TAU * max(ref, 1e-6)
    wts = np.exp((s - ref) / tau)
    cells = np.arange(-half, half + 1, dtype=np.float64) * r
    dth, ddx, ddy = np.meshgrid(rel, cells, cells, indexing="ij")
    d = np.stack([ddx.ravel(), ddy.ravel(), dth.ravel()])
    wv = wts.ravel()
    cov: NDArray[np.float64] = (d * wv) @ d.T / wv.sum()
    cov += np.diag([r * r / 12.0, r * r / 12.0, step * step / 12.0])
    return cov


def _stats_result(
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    pose: NDArray[np.float64],
    icp: ICPConfig,
    method: str,
    t0: float,
) -> MatchResult:
    """A converged `MatchResult` at ``pose`` with the ICP's final statistics (no iteration)."""
    out = _core.run_match(
        True, src, tgt, pose, icp.cell_size, 0, icp.translation_tol,
        math.radians(icp.rotation_tol_deg), False, math.inf, icp.trim_fraction, icp.huber_delta,
        icp.normal_radius, 3, icp.inlier_threshold, 1,
    )[0]  # fmt: skip
    _x, _y, _th, _it, _conv, _status, mean_d, med, hess, eig, n_in = out
    return MatchResult(
        pose=pose.copy(),
        iterations=0,
        converged=n_in > 0,
        reason=CONVERGED if n_in > 0 else NO_INLIERS,
        mean_residual=float(mean_d),
        median_residual=float(med),
        inlier_ratio=n_in / src.shape[0],
        inlier_threshold=icp.inlier_threshold,
        hessian=hess,
        eigenvalues=eig,
        time_s=time.perf_counter() - t0,
        n_source=src.shape[0],
        n_target=tgt.shape[0],
        method=method,
        n_inliers=int(n_in),
    )


def default_refine_config(config: CorrelativeConfig) -> ICPConfig:
    """The ICP settings of the refinement: correspondences within the smearing cutoff.

    The correlative pose is within a cell of the optimum, so pairs farther than
    ``max(3 sigma, 4 r)`` are parts of the scan the map does not explain.
    """
    return ICPConfig(
        max_correspondence_distance=max(CUTOFF_SIGMAS * config.sigma, 4 * config.resolution)
    )


def match_to_map(
    source_points: PointsLike,
    grid: LikelihoodGrid,
    initial: ArrayLike,
    config: CorrelativeConfig | None = None,
    *,
    window_xy: float | None = None,
    window_theta: float | None = None,
    icp_config: ICPConfig | None = None,
) -> tuple[MatchResult, CorrelativeResult]:
    """Correlative search, then (``config.refine``) point-to-line ICP against the map points.

    The ICP starts from the correlative pose. Its pose is kept only if the ICP converged or
    ran out of iterations and moved by at most ``REFINE_MAX_CELLS`` cells and
    ``REFINE_MAX_STEPS`` angular steps (2 and 2); otherwise the
    correlative pose stays (logged at debug level; the result still says ``"converged"``).

    Args:
        source_points: Scan points in the sensor frame (or a `LaserScan`).
        grid: The map's likelihood grid (its ``points`` are the ICP target).
        initial: Initial pose of the sensor in the map frame.
        config: See `correlative_match`.
        window_xy: See `correlative_match`.
        window_theta: See `correlative_match`.
        icp_config: Settings of the refinement; None = `default_refine_config`.

    Returns:
        ``(MatchResult, CorrelativeResult)``. The `MatchResult` has method
        ``"correlative+plicp"`` when the ICP pose was kept, else ``"correlative"`` (statistics
        at the correlative pose). When the search found nothing above ``min_score`` it has
        ``converged=False``, ``ok=False``, the initial pose and a reason.

    Raises:
        MatchingError: See `correlative_match`.
        ConfigError: See `correlative_match`.
    """
    t0 = time.perf_counter()
    cfg = _resolve_config(config, grid)
    corr = correlative_match(
        source_points, grid, initial, cfg, window_xy=window_xy, window_theta=window_theta
    )
    src = source_array(source_points, cfg.max_range)
    tgt = grid.points
    icp = icp_config or default_refine_config(cfg)
    if not corr.found:
        return _not_found(corr, src, tgt, icp, cfg.min_score, t0), corr
    if cfg.refine and src.shape[0] >= _MIN_REFINE_POINTS:
        refined = _refined(src, tgt, corr, icp, grid.resolution, t0)
        if refined is not None:
            return refined, corr
    return _stats_result(src, tgt, corr.pose, icp, "correlative", t0), corr


def _not_found(
    corr: CorrelativeResult,
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    icp: ICPConfig,
    min_score: float,
    t0: float,
) -> MatchResult:
    """The failed `MatchResult` of a search that found nothing above ``min_score``."""
    reason = f"no correlative match: best mean response below min_score {min_score}"
    return MatchResult(
        pose=corr.pose.copy(),
        iterations=0,
        converged=False,
        reason=reason,
        mean_residual=float("nan"),
        median_residual=float("nan"),
        inlier_ratio=0.0,
        inlier_threshold=icp.inlier_threshold,
        time_s=time.perf_counter() - t0,
        n_source=src.shape[0],
        n_target=tgt.shape[0],
        method="correlative",
    )


def _refined(
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    corr: CorrelativeResult,
    icp: ICPConfig,
    resolution: float,
    t0: float,
) -> MatchResult | None:
    """The point-to-line ICP result from the correlative pose, or None where it is not kept."""
    ref = icp_point_to_line(src, tgt, corr.pose, icp)
    if not ref.ok:
        logger.debug("correlative: ICP refinement failed (%s)", ref.reason)
        return None
    d = ref.pose - corr.pose
    moved = math.hypot(d[0], d[1])
    turned = abs(float(wrap_angle(float(d[2]))))
    max_t = REFINE_MAX_CELLS * resolution
    max_r = REFINE_MAX_STEPS * corr.theta_step
    if moved <= max_t and turned <= max_r:
        return dataclasses.replace(ref, method="correlative+plicp", time_s=time.perf_counter() - t0)
    logger.debug(
        "correlative: ICP refinement rejected (moved %.4f m, %.5f rad from the "
        "correlative pose; limits %.4f m, %.5f rad)",
        moved, turned, max_t, max_r,
    )  # fmt: skip
    return None


@dataclass(frozen=True)
class CorrelativeMatcher:
    """Scan-to-scan `Matcher`: the target scan becomes a likelihood grid, then `match_to_map`.

    Bad data never raises, as for the ICP matchers: fewer than 5 valid points in either scan
    or a non-finite initial guess give a result with ``ok=False`` and a reason.

    Attributes:
        name: Registry name.
        config: Settings (grid and search).
    """

    name: str = "correlative"
    config: CorrelativeConfig = field(default_factory=CorrelativeConfig)

    def __call__(
        self, source: PointsLike, target: PointsLike, initial: ArrayLike | None = None
    ) -> MatchResult:
        """Match ``source`` to ``target`` from ``initial`` (None = identity)."""
        t0 = time.perf_counter()
        src = as_points(source, "source")
        tgt = as_points(target, "target")
        init = initial_pose(initial)
        reason = None
        if not np.all(np.isfinite(init)):
            reason, init = "non-finite initial guess", np.zeros(3)
        elif src.shape[0] < _MIN_REFINE_POINTS or tgt.shape[0] < _MIN_REFINE_POINTS:
            reason = (
                f"too few valid points (source {src.shape[0]}, target {tgt.shape[0]}; "
                f"need {_MIN_REFINE_POINTS})"
            )
        if reason is not None:
            return MatchResult(
                pose=init, iterations=0, converged=False, reason=reason,
                mean_residual=float("nan"), median_residual=float("nan"), inlier_ratio=0.0,
                inlier_threshold=ICPConfig().inlier_threshold, time_s=time.perf_counter() - t0,
                n_source=src.shape[0], n_target=tgt.shape[0], method="correlative",
            )  # fmt: skip
        grid = LikelihoodGrid.from_points(tgt, self.config)
        result, _corr = match_to_map(src, grid, init, self.config)
        return dataclasses.replace(result, time_s=time.perf_counter() - t0)
