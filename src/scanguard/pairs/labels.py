"""Ground-truth labels of scan matches: error of the estimate against a reference relative pose.

For a pair ``(t-1, t)`` the matcher estimates the pose of the current sensor frame in the
previous one; the reference gives the true relative pose. Their difference is the *error
transform* ``E = inverse(reference) ⊕ estimate`` (in the current sensor frame). Three error
measures are derived from it:

* ``trans_error`` — ``|E.xy|`` (m),
* ``rot_error`` — ``|E.theta|`` (rad),
* ``disp_error`` — the mean displacement ``mean_i |E(p_i) - p_i|`` of the current scan's valid
  points ``p_i`` (m). It is what a mis-registered scan does to the map: a small rotation error
  moves far points a lot (lever arm), a translation error moves every point equally.

A pair is a **fault** (label 1) when any measure exceeds its fault limit, **normal** (label 0)
when every measure is below its normal limit, and **ambiguous** (label -1) otherwise. The gap
between the two limits keeps borderline matches out of training without hiding them: they stay
in the data and are reported separately.

Labels are never computed from non-finite errors: a pair whose error is NaN or infinite (a NaN
reference pose, for instance) has no known answer, so it is ambiguous (excluded from training
and evaluation), never a fault; `non_finite_errors` finds them so that callers report a count.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import model_validator

from scanguard.config import YamlModel
from scanguard.geometry import relative

NORMAL = 0
FAULT = 1
AMBIGUOUS = -1
LABEL_NAMES: dict[int, str] = {NORMAL: "normal", FAULT: "fault", AMBIGUOUS: "ambiguous"}


class LabelConfig(YamlModel):
    """Thresholds that turn match errors into labels.

    Attributes:
        fault_displacement: Mean point displacement (m) above which a match is a fault.
        normal_displacement: Mean point displacement (m) below which a match may be normal.
        fault_translation: Translation error (m) above which a match is a fault.
        normal_translation: Translation error (m) below which a match may be normal.
        fault_rotation_deg: Rotation error (deg) above which a match is a fault.
        normal_rotation_deg: Rotation error (deg) below which a match may be normal.
    """

    fault_displacement: float = 0.10
    normal_displacement: float = 0.075
    fault_translation: float = 0.15
    normal_translation: float = 0.10
    fault_rotation_deg: float = 2.0
    normal_rotation_deg: float = 1.0

    @model_validator(mode="after")
    def _ordered(self) -> LabelConfig:
        for name in ("displacement", "translation", "rotation_deg"):
            lo = getattr(self, f"normal_{name}")
            hi = getattr(self, f"fault_{name}")
            if not (0.0 < lo <= hi):
                raise ValueError(f"need 0 < normal_{name} ({lo}) <= fault_{name} ({hi})")
        return self

    @property
    def fault_rotation(self) -> float:
        """Fault rotation limit in radians."""
        return math.radians(self.fault_rotation_deg)

    @property
    def normal_rotation(self) -> float:
        """Normal rotation limit in radians."""
        return math.radians(self.normal_rotation_deg)


def mean_displacement(error: ArrayLike, points: ArrayLike) -> float:
    """Mean distance every point moves under the error transform.

    Args:
        error: Error transform ``(3,)`` (``inverse(reference) ⊕ estimate``).
        points: Current scan points ``(M, 2)`` in the current sensor frame.

    Returns:
        ``mean_i |E(p_i) - p_i|`` in metres; ``|E.xy|`` when there are no points (the sensor
        origin is then the only point we know moved).
    """
    e = np.asarray(error, dtype=np.float64).reshape(3)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] == 0:
        return float(math.hypot(e[0], e[1]))
    c, s = math.cos(e[2]), math.sin(e[2])
    # E(p) - p = (R - I) p + t, computed directly to avoid cancellation for tiny angles
    dx = (c - 1.0) * p[:, 0] - s * p[:, 1] + e[0]
    dy = s * p[:, 0] + (c - 1.0) * p[:, 1] + e[1]
    return float(np.mean(np.hypot(dx, dy)))


def pair_errors(
    estimate: ArrayLike, reference: ArrayLike, points: ArrayLike
) -> tuple[float, float, float]:
    """Errors of one match estimate against the reference relative pose.

    Args:
        estimate: Match estimate ``(3,)``: pose of the current sensor frame in the previous one.
        reference: True relative pose ``(3,)``, same convention.
        points: Valid points ``(M, 2)`` of the current scan in its sensor frame.

    Returns:
        ``(trans_error m, rot_error rad, disp_error m)``.
    """
    e = relative(np.asarray(reference, dtype=np.float64), np.asarray(estimate, dtype=np.float64))
    return (
        float(math.hypot(e[0], e[1])),
        float(abs(e[2])),
        mean_displacement(e, points),
    )


def assign_labels(
    trans_error: ArrayLike,
    rot_error: ArrayLike,
    disp_error: ArrayLike,
    config: LabelConfig | None = None,
    *,
    diverged: ArrayLike | None = None,
) -> NDArray[np.int8]:
    """Labels from errors (vectorised): 1 fault, 0 normal, -1 ambiguous.

    Args:
        trans_error: Translation errors (m), any shape.
        rot_error: Absolute rotation errors (rad), same shape.
        disp_error: Mean point displacements (m), same shape.
        config: Thresholds (defaults to `LabelConfig()`).
        diverged: Optional mask, same shape: matches known to have failed (no finite
            estimate). They are faults whatever their errors; this is the one way a pair
            without finite errors becomes a fault, and it must come from the match itself.

    Returns:
        int8 labels, same shape. A pair with any non-finite error is ambiguous (-1): its label
        is unknown, so it is never called a fault (or normal); count them with
        `non_finite_errors`.
    """
    cfg = config or LabelConfig()
    t = np.asarray(trans_error, dtype=np.float64)
    r = np.asarray(rot_error, dtype=np.float64)
    d = np.asarray(disp_error, dtype=np.float64)
    bad = non_finite_errors(t, r, d)
    with np.errstate(invalid="ignore"):
        fault = ~bad & (
            (d > cfg.fault_displacement) | (t > cfg.fault_translation) | (r > cfg.fault_rotation)
        )
        normal = (
            ~bad
            & ~fault
            & (d < cfg.normal_displacement)
            & (t < cfg.normal_translation)
            & (r < cfg.normal_rotation)
        )
    out = np.full(d.shape, AMBIGUOUS, dtype=np.int8)
    out[fault] = FAULT
    out[normal] = NORMAL
    if diverged is not None:
        out[np.broadcast_to(np.asarray(diverged, dtype=bool), out.shape)] = FAULT
    return out


def non_finite_errors(
    trans_error: ArrayLike, rot_error: ArrayLike, disp_error: ArrayLike
) -> NDArray[np.bool_]:
    """Mask of the pairs whose errors are not all finite (their label is unknown).

    Args:
        trans_error: Translation errors (m), any shape.
        rot_error: Rotation errors (rad), same shape.
        disp_error: Mean point displacements (m), same shape.

    Returns:
        Boolean mask, same shape: True where any of the three is NaN or infinite.
    """
    t = np.asarray(trans_error, dtype=np.float64)
    r = np.asarray(rot_error, dtype=np.float64)
    d = np.asarray(disp_error, dtype=np.float64)
    return np.asarray(~(np.isfinite(t) & np.isfinite(r) & np.isfinite(d)))
