"""The covariance of the motion between two graph nodes, compounded from the fused steps.

With ``odometry_noise: fused`` the graph's odometry factor takes the uncertainty the fused
motion model gives each scan's step (`scanguard.slam.motion.FusedMotion`: the wheels' noise
fitted on this recording, the judged match's Hessian, the prediction), instead of the
graph's fixed "1 m per m" model: along a corridor the wheels carry the weight the match
cannot, and where the wheels slip the step follows the match with the match's certainty.

The steps between two nodes are compounded to first order (Smith and Cheeseman): with the
accumulated increment ``A`` and the next step ``u`` (each ``(x, y, theta)`` in its start
frame), ``A' = A + u`` has ``J_A S_A J_A^T + J_u S_u J_u^T``. The result is then expressed as
gtsam's ``BetweenFactorPose2`` reads its noise (a perturbation on the right of the measured
increment) and moved from the robot frame to the sensor frame the graph's variables live in.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import compose, inverse


def pose2_adjoint(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """Adjoint ``(3, 3)`` of a 2D pose: ``T Exp(d) T^-1 = Exp(Ad_T d)`` (gtsam's ordering)."""
    x, y, th = (float(v) for v in pose)
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])


class StepCovariance:
    """Compounds the covariances of the steps since the last node.

    Args:
        laser_offset: Sensor pose in the robot frame (the graph's variables are sensor poses).
    """

    def __init__(self, laser_offset: NDArray[np.float64]) -> None:
        self._to_sensor = pose2_adjoint(inverse(np.asarray(laser_offset, dtype=np.float64)))
        self._inc = np.zeros(3)
        self._cov: NDArray[np.float64] | None = np.zeros((3, 3))

    def reset(self) -> None:
        """Start again at a new node (no motion, no uncertainty)."""
        self._inc = np.zeros(3)
        self._cov = np.zeros((3, 3))

    def add(self, step: NDArray[np.float64], covariance: NDArray[np.float64] | None) -> None:
        """One scan's robot-frame step and its covariance (None or non-finite: unknown).

        One step of unknown covariance makes the whole increment's unknown until `reset`.
        """
        if self._cov is None or covariance is None or not np.all(np.isfinite(covariance)):
            self._cov = None
        else:
            c, s = math.cos(self._inc[2]), math.sin(self._inc[2])
            ux, uy = float(step[0]), float(step[1])
            j_a = np.array([[1.0, 0.0, -s * ux - c * uy], [0.0, 1.0, c * ux - s * uy], [0, 0, 1]])
            j_u = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            self._cov = j_a @ self._cov @ j_a.T + j_u @ covariance @ j_u.T
        self._inc = compose(self._inc, step)

    def sensor_covariance(self) -> NDArray[np.float64] | None:
        """The covariance of the sensor-frame increment as gtsam reads it; None when unknown."""
        if self._cov is None:
            return None
        c, s = math.cos(self._inc[2]), math.sin(self._inc[2])
        # node-frame (x, y, theta) -> a perturbation in the frame of the increment's end
        b = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        local = b @ self._cov @ b.T
        out = self._to_sensor @ local @ self._to_sensor.T
        return np.asarray(0.5 * (out + out.T))
