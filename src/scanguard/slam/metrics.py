"""Trajectory error metrics: ATE / RPE (``evo``), Figure 19.

Planar poses are lifted to SE(3) (z = 0, yaw-only rotation) so that ``evo`` computes the
standard metrics exactly as it does for any other trajectory. The relation metric of the
Freiburg SLAM benchmark is `scanguard.slam.relations`.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.fsutil import save_figure
from scanguard.geometry import as_pose

if TYPE_CHECKING:
    pass

logger = logging.getLogger(__name__)


def to_evo(stamps: ArrayLike, poses: ArrayLike, name: str | None = None) -> object:
    """Convert SE(2) poses ``(N, 3)`` to an ``evo`` ``PoseTrajectory3D`` (z = 0).

    Returns:
        An ``evo.core.trajectory.PoseTrajectory3D`` (typed as object to keep evo optional at
        import time).
    """
    from evo.core.trajectory import PoseTrajectory3D

    p = as_pose(poses).reshape(-1, 3)
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    if t.shape[0] != p.shape[0]:
        raise ValueError(f"{t.shape[0]} stamps but {p.shape[0]} poses")
    xyz = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(p))])
    half = p[:, 2] / 2.0
    wxyz = np.column_stack([np.cos(half), np.zeros(len(p)), np.zeros(len(p)), np.sin(half)])
    return PoseTrajectory3D(
        positions_xyz=xyz, orientations_quat_wxyz=wxyz, timestamps=t, meta={"name": name or ""}
    )


@dataclass(frozen=True)
class TrajectoryErrors:
    """Errors of one trajectory against a reference.

    Attributes:
        ate_rmse: Absolute trajectory error, translation RMSE (m), after SE(3) Umeyama alignment
            (no scale) when ``aligned``.
        ate_max: Largest absolute translation error (m).
        rpe_trans_rmse: Relative pose error per ``delta`` frames, translation RMSE (m).
        rpe_rot_rmse_deg: Relative pose error per ``delta`` frames, rotation RMSE (deg).
        rpe_trans_mean: Mean relative translation error (m).
        delta: RPE frame distance.
        aligned: Whether ATE used alignment.
        n: Number of poses.
    """

    ate_rmse: float
    ate_max: float
    rpe_trans_rmse: float
    rpe_rot_rmse_deg: float
    rpe_trans_mean: float
    delta: int
    aligned: bool
    n: int

    def as_dict(self) -> dict[str, float | int | bool]:
        """Plain dict (for JSON/CSV)."""
        return asdict(self)


def trajectory_errors(
    stamps: ArrayLike,
    estimate: ArrayLike,
    reference: ArrayLike,
    *,
    delta: int = 1,
    align: bool = True,
) -> TrajectoryErrors:
    """ATE and RPE of ``estimate`` against ``reference`` (same stamps), computed with ``evo``.

    Args:
        stamps: Times ``(N,)``.
        estimate: Estimated robot poses ``(N, 3)``.
        reference: Reference robot poses ``(N, 3)``.
        delta: RPE frame distance (1 = per scan pair, i.e. the scan-matching error).
        align: Umeyama-align (rotation + translation) before the ATE.

    Returns:
        The errors.
    """
    from evo.core import metrics

    est = to_evo(stamps, estimate)
    ref = to_evo(stamps, reference)
    n = len(np.asarray(stamps).reshape(-1))
    est_a = copy.deepcopy(est)
    if align and n >= 3:
        try:
            est_a.align(ref, correct_scale=False)  # type: ignore[attr-defined]
        except Exception as exc:  # degenerate (e.g. static) trajectories cannot be aligned
            logger.debug("ATE alignment skipped: %s", exc)
            est_a = copy.deepcopy(est)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_a))
    ate = ape.get_all_statistics()
    if n > delta:
        rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta)
        rpe_t.process_data((ref, est))
        rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=delta)
        rpe_r.process_data((ref, est))
        st_t, st_r = rpe_t.get_all_statistics(), rpe_r.get_all_statistics()
        rt, rt_mean, rr = float(st_t["rmse"]), float(st_t["mean"]), float(st_r["rmse"])
    else:
        rt = rt_mean = rr = float("nan")
    return TrajectoryErrors(
        ate_rmse=float(ate["rmse"]),
        ate_max=float(ate["max"]),
        rpe_trans_rmse=rt,
        rpe_rot_rmse_deg=rr,
        rpe_trans_mean=rt_mean,
        delta=delta,
        aligned=align,
        n=n,
    )


def centroid_distance(
    previous: NDArray[np.floating], current: NDArray[np.floating], pose: ArrayLike
) -> float:
    """The paper's scan-matching error (Section 2.2, Figure 19).

    Euclidean distance between the centre of mass of the previous scan and that of the current
    scan after applying the match ``pose`` (current sensor frame in the previous one).

    Returns:
        The distance (m), NaN when either scan has no points.
    """
    if len(previous) == 0 or len(current) == 0:
        return float("nan")
    mu_q = np.asarray(previous).mean(axis=0, dtype=np.float64)
    mu_p = np.asarray(current).mean(axis=0, dtype=np.float64)
    return centroid_distance_from_means(mu_q, mu_p, pose)


def centroid_distance_from_means(
    previous_mean: ArrayLike, current_mean: ArrayLike, pose: ArrayLike
) -> float:
    """`centroid_distance` from the two scans' centres of mass ``(2,)`` (NaN if either is NaN)."""
    q = np.asarray(previous_mean, dtype=np.float64)
    x, y, th = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(3))
    px, py = (float(v) for v in np.asarray(current_mean, dtype=np.float64))
    c, s = math.cos(th), math.sin(th)
    return float(math.hypot(q[0] - (c * px - s * py + x), q[1] - (s * px + c * py + y)))


#: Marker styles of `save_trajectories_figure`'s ``markers``, in order.
_MARKER_STYLES: tuple[dict[str, Any], ...] = (
    {"marker": "o", "ms": 7, "mfc": "none", "mec": "0.55", "mew": 1.5},
    {"marker": "x", "ms": 5, "color": "tab:red", "mew": 1.2},
    {"marker": "+", "ms": 6, "color": "tab:purple", "mew": 1.2},
)


def save_trajectories_figure(
    trajectories: Mapping[str, NDArray[np.float64]],
    path: str | Path,
    reference: NDArray[np.float64] | None = None,
    title: str | None = None,
    markers: Mapping[str, NDArray[np.float64]] | None = None,
) -> Path:
    """Plot planar trajectories (and the reference, dashed black) into a PNG.

    Args:
        trajectories: Name -> poses ``(N, 3)``.
        path: The PNG.
        reference: Reference poses, dashed black.
        title: Figure title.
        markers: Label -> points ``(M, 2)`` drawn as markers over the lines (e.g. where the
            wheels were flagged); an empty array is left out of the legend.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 6.0))
    if reference is not None:
        ax.plot(reference[:, 0], reference[:, 1], "k--", lw=1.5, label="reference")
    for name, t in trajectories.items():
        ax.plot(t[:, 0], t[:, 1], "-", lw=1.0, label=name)
    for (label, pts), style in zip((markers or {}).items(), _MARKER_STYLES, strict=False):
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], linestyle="none", label=label, **style)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    out = save_figure(fig, Path(path), dpi=110)
    return out


def save_centroid_figure(
    errors: Mapping[str, NDArray[np.float64]], path: str | Path, title: str | None = None
) -> Path:
    """Bar chart of the mean centroid distance per method (the paper's Figure 19)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(errors)
    means = [float(np.nanmean(errors[k])) if np.isfinite(errors[k]).any() else 0.0 for k in names]
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2.0, 4.0))
    ax.bar(names, means, color=["tab:red", "tab:blue", "tab:green", "tab:gray"][: len(names)])
    for i, m in enumerate(means):
        ax.text(i, m, f"{m:.3f}", ha="center", va="bottom")
    ax.set_ylabel("mean centroid distance (m)")
    ax.set_title(title or "Scan-matching error (paper Fig. 19)")
    out = save_figure(fig, Path(path), dpi=110)
    return out


# --- Kümmerle et al. 2009: errors against reference relations ---------------------------------
