"""Straightforward numpy + ``scipy.spatial.cKDTree`` version of the paper's ICP.

Slow on purpose (it is the textbook transcription): it is the correctness reference for the
numba ICP in tests and the speed baseline in ``benchmarks/bench_icp.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from scanguard.matching.config import ICPConfig


def icp_point_to_point_reference(
    source: ArrayLike,
    target: ArrayLike,
    initial: ArrayLike | None = None,
    config: ICPConfig | None = None,
    workers: int = 1,
) -> tuple[NDArray[np.float64], int, bool]:
    """The paper's ICP with an SVD per iteration; same stop rules as `icp_point_to_point`.

    Args:
        source: Current points ``(M, 2)`` (finite).
        target: Previous points ``(K, 2)`` (finite).
        initial: Initial pose guess; None = identity.
        config: Stop rule and limits (``max_correspondence_distance`` is honoured;
            ``threads`` is not: see ``workers``).
        workers: Threads of each ``cKDTree.query`` (scipy's ``workers``), for a comparison
            at the same parallelism as ``ICPConfig.threads``.

    Returns:
        ``(pose (3,), iterations, converged)``.
    """
    cfg = config or ICPConfig()
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    tree = cKDTree(tgt)
    R = np.eye(2)
    t = np.zeros(2)
    if initial is not None:
        x, y, th = (float(v) for v in np.asarray(initial, dtype=np.float64).reshape(3))
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        t = np.array([x, y])
    max_d = cfg.max_correspondence_distance
    tol_r = math.radians(cfg.rotation_tol_deg)
    iterations = 0
    converged = False
    for _ in range(cfg.max_iterations):
        iterations += 1
        P = src @ R.T + t
        dist, idx = tree.query(
            P, distance_upper_bound=np.inf if max_d is None else max_d, workers=workers
        )
        ok = np.isfinite(dist)
        if ok.sum() < 3:
            break
        P = P[ok]
        Q = tgt[idx[ok]]
        mu_p = P.mean(axis=0)
        mu_q = Q.mean(axis=0)
        K = (Q - mu_q).T @ (P - mu_p)
        U, _s, Vt = np.linalg.svd(K)
        D = np.diag([1.0, np.linalg.det(U @ Vt)])  # reflection fix
        dR = U @ D @ Vt
        dt = mu_q - dR @ mu_p
        R = dR @ R
        t = dR @ t + dt
        dth = math.atan2(dR[1, 0], dR[0, 0])
        if np.hypot(*dt) < cfg.translation_tol and (cfg.stop_rule == "paper" or abs(dth) < tol_r):
            converged = True
            break
    pose = np.array([t[0], t[1], math.atan2(R[1, 0], R[0, 0])])
    return pose, iterations, converged
