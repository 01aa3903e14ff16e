"""SE(2) helpers on poses stored as ``[..., 3]`` arrays ``(x, y, theta)``.

All functions are vectorised: any leading batch shape is allowed and broadcast.
A pose ``a`` maps points from its local frame into the parent frame:
``p_parent = R(theta) @ p_local + (x, y)``.
"""

from __future__ import annotations

import math
from typing import TypeGuard

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(theta: ArrayLike) -> FloatArray:
    """Wrap angles to ``[-pi, pi)``.

    Args:
        theta: Angles in radians, any shape.

    Returns:
        The wrapped angles as float64.
    """
    t = np.asarray(theta, dtype=np.float64)
    return np.asarray((t + np.pi) % (2.0 * np.pi) - np.pi)


def as_pose(pose: ArrayLike) -> FloatArray:
    """Return ``pose`` as a float64 array with last dimension 3, validating the shape."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"a pose must have last dimension 3 (x, y, theta), got shape {p.shape}")
    return p


def compose(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Compose two poses: ``a ⊕ b`` (apply ``b`` in the frame of ``a``).

    Args:
        a: Pose(s) ``[..., 3]``.
        b: Pose(s) ``[..., 3]``.

    Returns:
        The composed pose(s), theta wrapped.
    """
    if _single(a) and _single(b):
        return _compose1(a.tolist(), b.tolist())
    a = as_pose(a)
    b = as_pose(b)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    th = wrap_angle(a[..., 2] + b[..., 2])
    return np.stack(np.broadcast_arrays(x, y, th), axis=-1)


def inverse(a: ArrayLike) -> FloatArray:
    """Return the inverse pose(s): composing a pose with it gives the identity."""
    if _single(a):
        return np.array(_inverse1(a.tolist()))
    a = as_pose(a)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def relative(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Pose of ``b`` expressed in the frame of ``a``: ``inverse(a) ⊕ b``."""
    if _single(a) and _single(b):
        return _compose1(_inverse1(a.tolist()), b.tolist())
    return compose(inverse(a), b)


# One pose at a time is what the per-scan loop asks for (hundreds of thousands of calls per
# log), where numpy's per-call overhead is ten times the arithmetic. The scalar forms below
# evaluate the very expressions of the array forms in the same order, with math's cos/sin
# and float %, which numpy's match bit for bit (tests/test_geometry.py checks it); angles
# that are not finite go the array way, since math.cos(inf) raises where np.cos gives NaN.
_TWO_PI = 2.0 * math.pi


def _single(p: object) -> TypeGuard[FloatArray]:
    """``p`` is one finite-angle float64 pose ``(3,)`` (the scalar fast path applies)."""
    return (
        type(p) is np.ndarray and p.shape == (3,) and p.dtype == np.float64 and math.isfinite(p[2])
    )


def _wrap1(t: float) -> float:
    return (t + math.pi) % _TWO_PI - math.pi


def _compose1(a: list[float], b: list[float]) -> FloatArray:
    c, s = math.cos(a[2]), math.sin(a[2])
    x = a[0] + c * b[0] - s * b[1]
    y = a[1] + s * b[0] + c * b[1]
    return np.array((x, y, _wrap1(a[2] + b[2])))


def _inverse1(a: list[float]) -> list[float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return [-(c * a[0] + s * a[1]), -(-s * a[0] + c * a[1]), _wrap1(-a[2])]


def transform_points(pose: ArrayLike, points: ArrayLike) -> NDArray[np.floating]:
    """Apply a single pose to ``(N, 2)`` points (keeps float32 input as float32).

    Args:
        pose: One pose ``(3,)``.
        points: Points ``(N, 2)`` in the pose's local frame.

    Returns:
        The points in the parent frame, same dtype as ``points`` if floating.
    """
    p = as_pose(pose)
    pts = np.asarray(points)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(np.float64)
    c, s = np.cos(p[2]), np.sin(p[2])
    rot = np.array([[c, -s], [s, c]], dtype=pts.dtype)
    return pts @ rot.T + np.asarray(p[:2], dtype=pts.dtype)


def pose_to_matrix(pose: ArrayLike) -> FloatArray:
    """Convert pose(s) ``[..., 3]`` to homogeneous matrices ``[..., 3, 3]``."""
    p = as_pose(pose)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    m = np.zeros((*p.shape[:-1], 3, 3))
    m[..., 0, 0] = c
    m[..., 0, 1] = -s
    m[..., 1, 0] = s
    m[..., 1, 1] = c
    m[..., 0, 2] = p[..., 0]
    m[..., 1, 2] = p[..., 1]
    m[..., 2, 2] = 1.0
    return m


def matrix_to_pose(m: ArrayLike) -> FloatArray:
    """Convert homogeneous matrices ``[..., 3, 3]`` to poses ``[..., 3]``."""
    mm = np.asarray(m, dtype=np.float64)
    th = np.arctan2(mm[..., 1, 0], mm[..., 0, 0])
    return np.stack([mm[..., 0, 2], mm[..., 1, 2], wrap_angle(th)], axis=-1)


def yaw_to_quaternion(theta: ArrayLike) -> FloatArray:
    """Yaw angle(s) to quaternions ``[..., 4]`` in ``(qx, qy, qz, qw)`` order."""
    t = np.asarray(theta, dtype=np.float64)
    z = np.zeros_like(t)
    return np.stack([z, z, np.sin(t / 2.0), np.cos(t / 2.0)], axis=-1)


def quaternion_to_yaw(q: ArrayLike) -> FloatArray:
    """Quaternion(s) ``[..., 4]`` in ``(qx, qy, qz, qw)`` order to yaw angle(s)."""
    qq = np.asarray(q, dtype=np.float64)
    x, y, z, w = qq[..., 0], qq[..., 1], qq[..., 2], qq[..., 3]
    return np.asarray(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def interpolate_poses(stamps: ArrayLike, poses: ArrayLike, query: ArrayLike) -> FloatArray:
    """Interpolate timestamped poses at query times (linear in x, y; shortest arc in theta).

    Queries outside ``[stamps[0], stamps[-1]]`` are clamped to the end poses.

    Args:
        stamps: Increasing times ``(M,)``.
        poses: Poses ``(M, 3)``.
        query: Times ``(N,)``.

    Returns:
        Poses ``(N, 3)``.
    """
    t = np.asarray(stamps, dtype=np.float64)
    p = as_pose(poses).reshape(-1, 3)
    q = np.asarray(query, dtype=np.float64)
    if t.size == 0:
        raise ValueError("cannot interpolate from an empty pose list")
    if t.size == 1:
        return np.repeat(p, q.size, axis=0)
    order = np.argsort(t, kind="stable")
    t, p = t[order], p[order]
    theta = np.unwrap(p[:, 2])
    x = np.interp(q, t, p[:, 0])
    y = np.interp(q, t, p[:, 1])
    th = wrap_angle(np.interp(q, t, theta))
    return np.stack([x, y, th], axis=-1)


def pose_error(estimate: ArrayLike, reference: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Translation (m) and absolute rotation (rad) of ``inverse(reference) ⊕ estimate``."""
    e = relative(reference, estimate)
    return np.hypot(e[..., 0], e[..., 1]), np.abs(e[..., 2])
