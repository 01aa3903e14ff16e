"""`MatchResult`: the estimate of a scan matcher plus what classical failure detectors look at."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

# Reasons a match reports (``MatchResult.reason``).
CONVERGED = "converged"
MAX_ITERATIONS = "max_iterations"
NO_INLIERS = "no source point within the inlier threshold of the target"
"""A match that stopped moving far from every target point: never "converged"."""


@dataclass(frozen=True, eq=False)
class MatchResult:
    """Outcome of matching a current scan (source) to a previous scan (target).

    Attributes:
        pose: Estimate ``(x, y, theta)`` of the source frame in the target frame:
            ``transform_points(pose, source)`` lands on the target.
        iterations: Iterations (updates) used.
        converged: The stop rule was met within the iteration cap.
        reason: ``"converged"``, ``"max_iterations"``, or why no match was possible
            (too few points, non-finite input, divergence, ...).
        mean_residual: Mean distance (m) from every transformed source point to its nearest
            target point at the final estimate (NaN when no match was possible).
        median_residual: Median of the same distances (m).
        inlier_ratio: Fraction of source points whose nearest target point is closer than
            ``inlier_threshold`` (an overlap measure).
        inlier_threshold: The distance (m) used for ``inlier_ratio``.
        hessian: Information matrix ``sum J_i^T J_i`` of the final alignment over the inlier
            pairs, with point-to-line Jacobians ``J_i = n_i^T [I | perp(p_i)]`` in
            ``(x, y, theta)`` (target frame); its small eigenvalues reveal degenerate
            directions (Zhang, Kaess & Singh 2016).
        eigenvalues: Eigenvalues of ``hessian``, ascending.
        time_s: Wall-clock time of the match (s).
        n_source: Valid (finite) source points used.
        n_target: Valid (finite) target points used.
        method: Name of the algorithm (``"icp_point_to_point"``, ``"icp_point_to_line"``).
        n_inliers: Number of inlier pairs (also the pairs in ``hessian``).
    """

    pose: NDArray[np.float64]
    iterations: int
    converged: bool
    reason: str
    mean_residual: float
    median_residual: float
    inlier_ratio: float
    inlier_threshold: float
    hessian: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    eigenvalues: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    time_s: float = 0.0
    n_source: int = 0
    n_target: int = 0
    method: str = ""
    n_inliers: int = 0

    @property
    def ok(self) -> bool:
        """A match was computed (enough valid points, finite result); it may not have converged."""
        return bool(np.all(np.isfinite(self.pose))) and self.reason in (CONVERGED, MAX_ITERATIONS)

    def metrics(self) -> dict[str, float]:
        """Flat numeric quality metrics (features for classical failure detectors).

        Keys: ``iterations``, ``converged`` (0/1), ``mean_residual``, ``median_residual``,
        ``inlier_ratio``, ``eig_min``, ``eig_mid``, ``eig_max``, ``condition_number``
        (``eig_max / eig_min``, inf when singular), ``eig_min_per_inlier``
        (``eig_min / n_inliers``, comparable across sensors), ``n_source``, ``n_target``,
        ``n_inliers``, ``translation`` (``|t|`` of the estimate, m), ``rotation``
        (``|theta|``, rad), ``ok`` (0/1). Residuals are NaN when no match was possible.
        Wall-clock time is deliberately left out: it is not reproducible.
        """
        ev = np.asarray(self.eigenvalues, dtype=np.float64)
        emin, emid, emax = (float(v) for v in ev)
        cond = emax / emin if emin > 0 else float("inf")
        return {
            "iterations": float(self.iterations),
            "converged": float(self.converged),
            "mean_residual": float(self.mean_residual),
            "median_residual": float(self.median_residual),
            "inlier_ratio": float(self.inlier_ratio),
            "eig_min": emin,
            "eig_mid": emid,
            "eig_max": emax,
            "condition_number": float(cond),
            "eig_min_per_inlier": emin / self.n_inliers if self.n_inliers > 0 else 0.0,
            "n_source": float(self.n_source),
            "n_target": float(self.n_target),
            "n_inliers": float(self.n_inliers),
            "translation": float(np.hypot(self.pose[0], self.pose[1])),
            "rotation": float(abs(self.pose[2])),
            "ok": float(self.ok),
        }
