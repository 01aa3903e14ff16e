"""What the pair image cannot show: how far the match disagrees with the odometry.

A robot sliding along a featureless corridor leaves the pair image unchanged whether the
matcher got the slide right or not; the wheel odometry, however, disagrees with a wrong
match. The disagreement is the match increment seen from the odometry increment,
``e = inverse(odometry) ⊕ estimate`` (both in the previous sensor frame), in units of the
odometry noise model (`OdometryNoise`, the same model the dataset uses to simulate odometry):

* ``odom_trans_z = |e.xy| / sigma_xy``,
* ``odom_rot_z = |e.theta| / sigma_theta``,
* ``has_odometry``: 1 where the pair has odometry, 0 where it has none (a mask).

Where a pair has no odometry both z values are 0 and ``has_odometry`` is 0, so one model
serves recordings with and without odometry: the mask's weight tells the model what "no
information" means. Training hides the odometry of a random share of the pairs
(`scanguard.detect.train_config.TrainConfig.odometry_dropout`) so that the model learns both cases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from scanguard.config import YamlModel
from scanguard.geometry import relative

__all__ = [
    "ODOMETRY_FEATURES",
    "NoiseFit",
    "OdometryNoise",
    "fit_odometry_noise",
    "odometry_disagreement",
    "odometry_sigmas",
]

#: Feature names of the odometry input (see the module docstring).
ODOMETRY_FEATURES: tuple[str, ...] = ("odom_trans_z", "odom_rot_z", "has_odometry")


class OdometryNoise(YamlModel):
    """Noise model of wheel odometry per step between consecutive scans.

    It serves twice: to simulate odometry from reference poses (for logs without usable
    odometry, `scanguard.dataset.labelling.simulated_odometry_steps`) and to express the
    disagreement between a match and the odometry in standard deviations
    (`odometry_disagreement`). Each relative motion ``(dx, dy, dtheta)`` has zero-mean
    Gaussian noise with standard deviations
    ``sigma_xy = trans_floor + trans_per_m * d`` (per axis) and
    ``sigma_theta = rad(rot_floor_deg) + rot_per_rad * |dtheta| + rad(rot_per_m_deg) * d``,
    where ``d`` is the distance travelled.

    Attributes:
        trans_floor: Translation noise at standstill (m).
        trans_per_m: Translation noise per metre travelled.
        rot_floor_deg: Rotation noise at standstill (deg).
        rot_per_rad: Rotation noise per radian turned.
        rot_per_m_deg: Rotation noise per metre travelled (deg/m).
        seed: Seed of simulated odometry (combined with the sequence name).
    """

    trans_floor: float = Field(default=0.01, ge=0)
    trans_per_m: float = Field(default=0.05, ge=0)
    rot_floor_deg: float = Field(default=0.5, ge=0)
    rot_per_rad: float = Field(default=0.05, ge=0)
    rot_per_m_deg: float = Field(default=1.0, ge=0)
    seed: int = 0


def odometry_sigmas(
    steps: ArrayLike, noise: OdometryNoise
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-axis translation and rotation standard deviations ``(N,)`` of steps ``(N, 3)``."""
    s = np.asarray(steps, dtype=np.float64).reshape(-1, 3)
    d = np.hypot(s[:, 0], s[:, 1])
    s_xy = noise.trans_floor + noise.trans_per_m * d
    s_th = (
        math.radians(noise.rot_floor_deg)
        + noise.rot_per_rad * np.abs(s[:, 2])
        + math.radians(noise.rot_per_m_deg) * d
    )
    return s_xy, s_th


# A zero-noise model would divide by zero; these floors keep the z values finite and large.
_MIN_SIGMA_XY = 1e-4
_MIN_SIGMA_TH = 1e-5


def odometry_disagreement(
    estimate: ArrayLike, odometry: ArrayLike | None, noise: OdometryNoise | None = None
) -> dict[str, NDArray[np.float64]]:
    """Odometry features ``{name: (N,)}`` of matched pairs (`ODOMETRY_FEATURES`).

    Args:
        estimate: ``(N, 3)`` match estimates: pose of the current sensor frame in the previous.
        odometry: ``(N, 3)`` odometry increments in the same (sensor) frame convention; a row
            with any non-finite value, or ``None`` for all, means "no odometry".
        noise: Noise model (default `OdometryNoise()`).

    Returns:
        ``odom_trans_z``, ``odom_rot_z`` (0 without odometry; ``inf`` for a non-finite
        estimate with odometry: the match failed), ``has_odometry`` (1.0 / 0.0) and
        ``odom_max_z``, the larger of the two z values (the classical ``odometry`` baseline's
        score, `scanguard.detect.baselines.registry.ODOMETRY_BASELINES`).
    """
    est = np.asarray(estimate, dtype=np.float64).reshape(-1, 3)
    n = est.shape[0]
    if odometry is None:
        odo = np.full((n, 3), np.nan)
    else:
        odo = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
        if odo.shape[0] != n:
            raise ValueError(f"{n} estimates but {odo.shape[0]} odometry increments")
    has = np.all(np.isfinite(odo), axis=1)
    tz = np.zeros(n)
    rz = np.zeros(n)
    if has.any():
        o = odo[has]
        e = relative(o, est[has])
        s_xy, s_th = odometry_sigmas(o, noise or OdometryNoise())
        with np.errstate(invalid="ignore"):
            t = np.hypot(e[:, 0], e[:, 1]) / np.maximum(s_xy, _MIN_SIGMA_XY)
            r = np.abs(e[:, 2]) / np.maximum(s_th, _MIN_SIGMA_TH)
        tz[has] = np.where(np.isfinite(t), t, np.inf)
        rz[has] = np.where(np.isfinite(r), r, np.inf)
    return {
        "odom_trans_z": tz,
        "odom_rot_z": rz,
        "has_odometry": has.astype(np.float64),
        "odom_max_z": np.maximum(tz, rz),
    }


#: Medians of ``|e| / sigma`` when a match agrees with the odometry up to its noise: the
#: translation z is the length of two N(0, 1) components (Rayleigh), the rotation z the size
#: of one (half-normal).
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
HALF_NORMAL_MEDIAN = 0.6744897501960817


@dataclass(frozen=True)
class NoiseFit:
    """A noise model fitted to one robot's recording (`fit_odometry_noise`).

    Attributes:
        noise: The fitted model (the base model scaled).
        trans_scale: Factor on the base model's translation noise (>= 1).
        rot_scale: Factor on the base model's rotation noise (>= 1).
        n_pairs: Matched pairs with odometry the fit used (0: too few, base model kept).
    """

    noise: OdometryNoise
    trans_scale: float
    rot_scale: float
    n_pairs: int


def fit_odometry_noise(
    estimates: ArrayLike,
    odometry: ArrayLike,
    base: OdometryNoise | None = None,
    *,
    min_pairs: int = 30,
) -> NoiseFit:
    """This robot's odometry noise, fitted from its own matches (no reference needed).

    Under the base model the disagreement of a match that is right, with odometry as noisy
    as the model says, has median z `RAYLEIGH_MEDIAN` (translation) and `HALF_NORMAL_MEDIAN`
    (rotation). A robot whose odometry is noisier shows larger medians; the base model's
    translation and rotation terms are scaled by the ratio, so that the detector reads
    disagreements in this robot's own units. The median ignores a minority of faulty
    matches; the scales never go below 1 (a recording never makes the model stricter than
    the one it was trained with).

    Args:
        estimates: ``(N, 3)`` match estimates (sensor frame).
        odometry: ``(N, 3)`` odometry increments in the same frame.
        base: The model to scale (default `OdometryNoise()`).
        min_pairs: Fewer usable pairs keep the base model.

    Returns:
        The fit; its ``noise`` keeps the base model's ``seed``.
    """
    base = base or OdometryNoise()
    d = odometry_disagreement(estimates, odometry, base)
    tz, rz = d["odom_trans_z"], d["odom_rot_z"]
    ok = (d["has_odometry"] > 0) & np.isfinite(tz) & np.isfinite(rz)
    n = int(ok.sum())
    if n < min_pairs:
        return NoiseFit(base, 1.0, 1.0, 0)
    st = max(1.0, float(np.median(tz[ok])) / RAYLEIGH_MEDIAN)
    sr = max(1.0, float(np.median(rz[ok])) / HALF_NORMAL_MEDIAN)
    noise = base.model_copy(
        update={
            "trans_floor": base.trans_floor * st,
            "trans_per_m": base.trans_per_m * st,
            "rot_floor_deg": base.rot_floor_deg * sr,
            "rot_per_rad": base.rot_per_rad * sr,
            "rot_per_m_deg": base.rot_per_m_deg * sr,
        }
    )
    return NoiseFit(noise, st, sr, n)
