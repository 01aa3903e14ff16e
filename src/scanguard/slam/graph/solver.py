"""The solver of the ``graph`` back end: gtsam's iSAM2, with the batch graph kept beside it.

`PoseGraphSolver` adds factors to iSAM2 and to a plain factor graph holding every factor (the
batch Levenberg-Marquardt pass reads that one), keeps the current estimates of the node poses
as an array, and rebuilds iSAM2 when it refuses an (almost) indeterminate system.
`rotate_cov` / `well_posed` prepare a response-surface covariance for a between-factor.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import BackendError

logger = logging.getLogger(__name__)


def rotate_cov(cov: NDArray[np.float64], theta: float) -> NDArray[np.float64]:
    """``cov`` (x, y, theta) expressed in a frame rotated by ``theta``: ``R^T cov R``."""
    c, s = math.cos(theta), math.sin(theta)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out: NDArray[np.float64] = r.T @ cov @ r
    return well_posed(0.5 * (out + out.T))


#: gtsam's M-estimator of each ``robust_kernel`` setting.
KERNELS = {"cauchy": "Cauchy", "huber": "Huber", "geman_mcclure": "GemanMcClure", "dcs": "DCS"}


def closure_factor(
    gtsam: Any,
    target: int,
    node: int,
    pose: NDArray[np.float64],
    covariance: NDArray[np.float64],
    kernel: str,
    scale: float,
) -> Any:
    """A one-factor graph: the closure ``target -> node`` under a robust kernel (or none).

    ``covariance`` is in ``target``'s frame rotated to the closure's (`rotate_cov`).
    """
    noise: Any = gtsam.noiseModel.Gaussian.Covariance(rotate_cov(covariance, float(pose[2])))
    if kernel != "none":
        estimator = getattr(gtsam.noiseModel.mEstimator, KERNELS[kernel])
        noise = gtsam.noiseModel.Robust.Create(estimator.Create(scale), noise)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose2(target, node, gtsam.Pose2(*pose), noise))
    return graph


def well_posed(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """``cov`` with its eigenvalues kept within [1e-8, 1e4].

    A response surface can be nearly singular (a sharp peak in one direction, none in
    another); iSAM2 refuses such a system as indeterminate.
    """
    if not np.all(np.isfinite(cov)):
        return np.diag([1e4, 1e4, 1e4])
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.clip(w, 1e-8, 1e4)
    out: NDArray[np.float64] = (v * w) @ v.T
    return 0.5 * (out + out.T)


def _new_isam(gtsam: Any, partial: bool = False) -> Any:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.01)
    params.relinearizeSkip = 1
    # partial: the relinearization check descends from the root only through cliques
    # whose variables moved beyond the threshold, instead of testing every variable at
    # every update (O(nodes) per node on a long log)
    params.enablePartialRelinearizationCheck = partial
    return gtsam.ISAM2(params)


class PoseGraphSolver:
    """iSAM2 over the node poses (keys ``0..n-1``), plus the batch graph of every factor.

    Args:
        gtsam: The ``gtsam`` module (imported by the back end).
        stats: The back end's counters (``solver_refusals`` and ``time_isam_s`` are counted
            here).
        window: Nodes behind the newest whose estimates are re-read after a plain update.
        partial_relinearization: See `GraphConfig.partial_relinearization`.

    Attributes:
        isam: The iSAM2 instance.
        graph: Every factor that went in (the batch pass optimises it).
        est: Current estimates of the node poses ``(n, 3)``.
    """

    def __init__(
        self,
        gtsam: Any,
        stats: dict[str, float],
        window: int,
        *,
        partial_relinearization: bool = False,
    ) -> None:
        self._gtsam = gtsam
        self.stats = stats
        self.window = window
        self._partial = partial_relinearization
        self.isam = _new_isam(gtsam, partial_relinearization)
        self.graph = gtsam.NonlinearFactorGraph()
        self.est: NDArray[np.float64] = np.zeros((0, 3))

    def commit(
        self,
        graph: Any,
        values: Any,
        n: int,
        *,
        refresh_all: bool = False,
        essential: Any = None,
    ) -> bool:
        """Add factors (and values) to iSAM2 and to the batch graph; refresh the estimates.

        Args:
            graph: The new factors.
            values: Initial values of the new variables.
            n: Number of nodes after this update.
            refresh_all: Re-read every estimate (after a loop closure).
            essential: The factors to keep if iSAM2 refuses ``graph`` as an (almost)
                indeterminate system (None: keep nothing). The solver is then rebuilt from
                the accepted factors plus these, at the current estimates.

        Returns:
            Whether ``graph`` went in whole.
        """
        t0 = time.perf_counter()
        whole = True
        try:
            self.isam.update(graph, values)
        except RuntimeError as exc:
            whole = False
            self.stats["solver_refusals"] += 1
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            logger.warning(
                "iSAM2 refused %d new factor(s) (%s); keeping %d and rebuilding the solver",
                graph.size(),
                first,
                0 if essential is None else essential.size(),
            )
            graph = essential if essential is not None else self._gtsam.NonlinearFactorGraph()
            self._rebuild(graph, values, n)
            refresh_all = True
        for i in range(graph.size()):
            self.graph.add(graph.at(i))
        if refresh_all or self.est.shape[0] + 1 < n:
            self.est = self.values_to_array(self.isam.calculateEstimate(), n)
        else:
            # iSAM2 moves old variables little without a loop closure; refreshing only the
            # recent ones keeps each update O(window) instead of O(nodes)
            est = np.empty((n, 3))
            est[: self.est.shape[0]] = self.est
            lo = max(0, n - self.window - 2)
            for key in range(lo, n):
                p = self.isam.calculateEstimatePose2(key)
                est[key] = (p.x(), p.y(), p.theta())
            self.est = est
        self.stats["time_isam_s"] += time.perf_counter() - t0
        return whole

    def withdraw(self, indices: list[int], n: int) -> None:
        """Take the factors at ``indices`` of `graph` out, and re-solve from the current estimates.

        iSAM2 keeps its own factor numbering (a rebuild after a refusal renumbers it), so the
        factors leave the batch graph and iSAM2 is rebuilt from what is left: rare (a group
        of far closures entering), and a rebuild costs one batch update.
        """
        t0 = time.perf_counter()
        for i in indices:
            self.graph.remove(i)
        self._rebuild(self._gtsam.NonlinearFactorGraph(), self._gtsam.Values(), n)
        self.est = self.values_to_array(self.isam.calculateEstimate(), n)
        self.stats["time_isam_s"] += time.perf_counter() - t0

    def _rebuild(self, extra: Any, values: Any, n: int) -> None:
        """A fresh iSAM2 over every accepted factor plus ``extra``, at the current estimates.

        Raises:
            BackendError: The solver refuses even that (the graph itself is broken).
        """
        gtsam = self._gtsam
        initial = gtsam.Values()
        for key in range(self.est.shape[0]):
            initial.insert(key, gtsam.Pose2(*self.est[key]))
        for key in values.keys():  # noqa: SIM118 (gtsam.Values is not a dict)
            if not initial.exists(key):
                initial.insert(key, values.atPose2(key))
        full = gtsam.NonlinearFactorGraph()
        for i in range(self.graph.size()):
            f = self.graph.at(i)
            if f is not None:
                full.add(f)
        for i in range(extra.size()):
            full.add(extra.at(i))
        self.isam = _new_isam(gtsam, self._partial)
        try:
            self.isam.update(full, initial)
        except RuntimeError as exc:
            raise BackendError(
                f"graph back end: the pose graph ({n} nodes) cannot be solved: "
                f"{str(exc).strip().splitlines()[0] if str(exc).strip() else exc!r}"
            ) from None

    def values_to_array(self, values: Any, n: int) -> NDArray[np.float64]:
        """The poses of keys ``0..n-1`` in ``values`` as an ``(n, 3)`` array.

        Raises:
            BackendError: ``values`` does not hold exactly ``n`` poses.
        """
        # keys are the node indices 0..n-1, which extractPose2 returns in order (one C++
        # call instead of a Python loop: this runs after every loop closure)
        out = np.asarray(self._gtsam.utilities.extractPose2(values), dtype=np.float64)
        out = out.reshape(-1, 3)
        if out.shape[0] != n:
            raise BackendError(
                f"graph back end: the solver holds {out.shape[0]} poses for {n} nodes"
            )
        return out.copy()


__all__ = ["PoseGraphSolver", "rotate_cov", "well_posed"]
