"""Is a loop closure consistent with the graph? The gate at entry and the final check.

A closure the judge accepted still enters the graph only when the correction it claims is one
the graph can account for (`closure_consistent`, ``GraphConfig.closure_gate_sigmas``): within
what a loop search could have proposed (its windows), and within some standard deviations of
the graph's own uncertainty about the two nodes, taken generously. A wrong closure entered
from elsewhere (a judge's mistake on a claim the search could not make, or one injected on
purpose) is refused before its pull moves the estimates that place the local maps and steer
the next searches. After the batch pass, the optional final check measures each accepted
closure against the optimised graph (`final_residual_sigmas`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import relative, wrap_angle
from scanguard.slam.graph.closure import ClosureCandidate, ClosureRecord
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.loop_search import reach_from_marginal, relative_covariance
from scanguard.slam.graph.solver import rotate_cov

#: What the ICP refinement of a loop match may add to the search windows (m, rad).
REACH_MARGIN_XY = 0.25
REACH_MARGIN_THETA = 0.1


def search_reach_limits(
    cfg: GraphConfig, cov: NDArray[np.float64] | None = None
) -> tuple[float, float]:
    """The largest correction a loop search can propose (translation per axis m, heading rad).

    The coarse window plus the fine one plus a margin for the ICP refinement. When the reach
    follows the uncertainty (``loop_search_sigmas``), the coarse window is that of a wide
    search from the node whose marginal covariance is ``cov`` (`reach_from_marginal`, what
    the search itself uses), or, without one, the widest any search can reach.
    """
    fine_xy = cfg.loop_fine.window_xy + REACH_MARGIN_XY
    fine_theta = cfg.loop_fine.window_theta + REACH_MARGIN_THETA
    if cfg.loop_search_sigmas > 0 and cov is None:
        return cfg.loop_search_max_radius + fine_xy, math.pi
    reach = reach_from_marginal(cov, cfg)
    return reach.window_xy + fine_xy, min(reach.window_theta + fine_theta, math.pi)


def closure_sigmas(
    candidate: ClosureCandidate, est: NDArray[np.float64], isam: Any, cfg: GraphConfig
) -> float:
    """How many standard deviations of the graph's uncertainty the closure's claim lies off.

    The larger of translation and heading, against a generous bound of the two nodes'
    relative uncertainty: their marginals against the first node (iSAM2; the largest
    eigenvalue of each position covariance, the heading acting over the distance between
    them) rather than against each other, plus the closure's own covariance, so that a
    closure after a drift the graph can account for still enters. Infinite for a correction
    beyond what a loop search from the newer node could propose now (`search_reach_limits`);
    0 when gtsam cannot form a marginal (after the widest window's check).

    Args:
        candidate: The closure.
        est: The current node estimates ``(M, 3)``.
        isam: The iSAM2 instance that holds them.
        cfg: The back end's configuration.
    """
    t, k = candidate.target_node, candidate.node
    est_rel = relative(est[t], est[k])
    err = np.asarray(candidate.pose, dtype=np.float64) - est_rel
    err[2] = wrap_angle(err[2])
    cov_t: NDArray[np.float64] | None = None
    cov_k: NDArray[np.float64] | None = None
    try:
        cov_t = np.asarray(isam.marginalCovariance(t), dtype=np.float64)
        cov_k = np.asarray(isam.marginalCovariance(k), dtype=np.float64)
    except RuntimeError:
        cov_t = cov_k = None
    window_cov = cov_k
    if cov_k is not None and cfg.loop_window == "relative":
        window_cov = relative_covariance(isam, t, k, est_rel)
    reach_xy, reach_theta = search_reach_limits(cfg, window_cov)
    # the search window is a square in the target's frame, as the claim is
    if max(abs(err[0]), abs(err[1])) > reach_xy or abs(float(err[2])) > reach_theta:
        return math.inf
    if cov_t is None or cov_k is None:
        return 0.0
    cov_c = np.asarray(candidate.covariance, dtype=np.float64) * cfg.match_covariance_scale
    var_xy = sum(float(np.linalg.eigvalsh(c[:2, :2])[-1]) for c in (cov_t, cov_k, cov_c))
    var_xy += float(est_rel[0] ** 2 + est_rel[1] ** 2) * float(max(cov_t[2, 2], cov_k[2, 2]))
    var_th = float(cov_t[2, 2] + cov_k[2, 2] + cov_c[2, 2])
    d_xy = math.hypot(err[0], err[1]) / math.sqrt(max(var_xy, 1e-12))
    d_th = abs(float(err[2])) / math.sqrt(max(var_th, 1e-12))
    return max(d_xy, d_th)


def closure_consistent(
    record: ClosureRecord, est: NDArray[np.float64], isam: Any, cfg: GraphConfig
) -> bool:
    """Whether the closure may enter (``closure_gate_sigmas``; always, when it is 0).

    Sets the record's ``gate_sigmas`` and, when refused, ``inconsistent``.
    """
    if cfg.closure_gate_sigmas <= 0:
        return True
    record.gate_sigmas = closure_sigmas(record.candidate, est, isam, cfg)
    record.inconsistent = record.gate_sigmas > cfg.closure_gate_sigmas
    return not record.inconsistent


def final_residual_sigmas(candidate: ClosureCandidate, est: NDArray[np.float64]) -> float:
    """The closure's Mahalanobis residual against optimised estimates (the final check)."""
    opt = relative(est[candidate.target_node], est[candidate.node])
    err = relative(np.asarray(candidate.pose), opt)
    err[2] = wrap_angle(err[2])
    cov = rotate_cov(np.asarray(candidate.covariance), float(candidate.pose[2]))
    d2 = float(err @ np.linalg.solve(cov, err))
    return math.sqrt(max(d2, 0.0))


__all__ = [
    "REACH_MARGIN_THETA",
    "REACH_MARGIN_XY",
    "closure_consistent",
    "closure_sigmas",
    "final_residual_sigmas",
    "search_reach_limits",
]
