"""GMapping's odometry motion model (OpenSLAM ``motionmodel.cpp``, ``drawFromMotion``).

The odometry step between two odometry poses is expressed in the frame of the older one,
``(dx, dy, dtheta)``; each particle moves by that step plus zero-mean Gaussian noise whose
standard deviations grow with the step (parameter naming as in `GMappingConfig`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.geometry import compose, relative, wrap_angle


def motion_sigma(
    step: ArrayLike, srr: float, srt: float, str_: float, stt: float
) -> NDArray[np.float64]:
    """Standard deviations ``(sx, sy, stheta)`` of the noise of an odometry ``step`` (..., 3)."""
    d = np.abs(np.asarray(step, dtype=np.float64))
    sxy = 0.3 * srr
    out = np.empty(d.shape)
    out[..., 0] = srr * d[..., 0] + str_ * d[..., 2] + sxy * d[..., 1]
    out[..., 1] = srr * d[..., 1] + str_ * d[..., 2] + sxy * d[..., 0]
    out[..., 2] = stt * d[..., 2] + srt * np.hypot(d[..., 0], d[..., 1])
    return out


def sample_motion(
    poses: ArrayLike,
    odom_old: ArrayLike,
    odom_new: ArrayLike,
    srr: float,
    srt: float,
    str_: float,
    stt: float,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Move every particle pose ``(P, 3)`` by the odometry step from ``odom_old`` to ``odom_new``.

    Returns:
        The new poses ``(P, 3)``: ``pose (+) (step + noise)``, noise drawn from `motion_sigma`.
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    step = relative(odom_old, odom_new).reshape(3)
    noise = rng.standard_normal((len(p), 3)) * motion_sigma(step, srr, srt, str_, stt)
    noisy = step[None, :] + noise
    noisy[:, 2] = wrap_angle(noisy[:, 2])
    return compose(p, noisy)
