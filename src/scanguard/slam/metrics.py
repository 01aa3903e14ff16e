"""Trajectory error metrics: ATE / RPE (``evo``), Figure 19, Kümmerle et al. 2009 relations.

Planar poses are lifted to SE(3) (z = 0, yaw-only rotation) so that ``evo`` computes the
standard metrics exactly as it does for any other trajectory. `relation_errors` scores a
trajectory against the reference relations of the Freiburg SLAM benchmark.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import InputError
from scanguard.fsutil import save_figure
from scanguard.geometry import as_pose, relative, wrap_angle

if TYPE_CHECKING:
    from scanguard.io.relations import Relations

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


def save_trajectories_figure(
    trajectories: Mapping[str, NDArray[np.float64]],
    path: str | Path,
    reference: NDArray[np.float64] | None = None,
    title: str | None = None,
) -> Path:
    """Plot planar trajectories (and the reference, dashed black) into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 6.0))
    if reference is not None:
        ax.plot(reference[:, 0], reference[:, 1], "k--", lw=1.5, label="reference")
    for name, t in trajectories.items():
        ax.plot(t[:, 0], t[:, 1], "-", lw=1.0, label=name)
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

PUBLISHED_RELATION_ERRORS: dict[str, dict[str, tuple[float, float]]] = {
    "intel": {
        "scan matching": (0.220, 0.296),
        "RBPF (GMapping, 50 particles)": (0.070, 0.083),
        "graph mapping": (0.031, 0.026),
    },
    "fr079": {
        "scan matching": (0.258, 0.427),
        "RBPF (GMapping, 50 particles)": (0.061, 0.044),
        "graph mapping": (0.056, 0.042),
    },
    "aces": {
        "scan matching": (0.173, 0.614),
        "RBPF (GMapping, 50 particles)": (0.060, 0.049),
        "graph mapping": (0.044, 0.044),
    },
}
"""Absolute translational relation error (m), mean and std, of Kümmerle et al. 2009, Table 1,
by recording (``"intel"``, ``"fr079"``, ``"aces"``) and method."""


def published_for(path: str | Path) -> dict[str, tuple[float, float]] | None:
    """The published relation errors of the recording ``path`` belongs to.

    The recording is recognised by the start of the file name (``intel.clf.gz`` ->
    ``"intel"``, ``fr079.relations`` -> ``"fr079"``, ``aces...`` -> ``"aces"``).

    Returns:
        A copy of the row of `PUBLISHED_RELATION_ERRORS` (method -> (mean, std) in m), or None
        for another recording.
    """
    name = Path(path).name.lower()
    for key, row in PUBLISHED_RELATION_ERRORS.items():
        if name.startswith(key):
            return dict(row)
    return None


@dataclass(frozen=True)
class RelationErrors:
    """Errors of a trajectory against reference relations (Kümmerle et al. 2009).

    ``n_matched + n_unmatched`` relations passed the ``max_dt`` filter (all of them without
    one); the other ``n_relations - n_matched - n_unmatched`` were left out by it.

    Attributes:
        n_relations: Relations in the file.
        n_matched: Relations used: both stamps found among the scan stamps, finite poses.
        n_unmatched: Relations within ``max_dt`` that could not be used (a stamp not found
            among the scan stamps, or a non-finite estimated pose).
        n_ambiguous_stamps: Relations within ``max_dt`` touching a stamp that occurs for more
            than one scan (the first scan in file order was used).
        trans_mean: Mean absolute translational error (m).
        trans_std: Its population standard deviation (m).
        trans_sq_mean: Mean squared translational error (m²).
        trans_sq_std: Its population standard deviation (m²).
        rot_mean_deg: Mean absolute rotational error (deg).
        rot_std_deg: Its population standard deviation (deg).
        rot_sq_mean: Mean squared rotational error (deg²).
        rot_sq_std: Its population standard deviation (deg²).
        max_dt: Only relations with ``|t2 - t1| <= max_dt`` (s) were considered; None: all.
    """

    n_relations: int
    n_matched: int
    n_unmatched: int
    n_ambiguous_stamps: int
    trans_mean: float
    trans_std: float
    trans_sq_mean: float
    trans_sq_std: float
    rot_mean_deg: float
    rot_std_deg: float
    rot_sq_mean: float
    rot_sq_std: float
    max_dt: float | None

    @property
    def n_selected(self) -> int:
        """Relations that passed the ``max_dt`` filter (matched or not)."""
        return self.n_matched + self.n_unmatched

    def as_dict(self) -> dict[str, float | int | None]:
        """Plain dict (for JSON/CSV)."""
        return asdict(self)


def _micros(t: NDArray[np.float64]) -> NDArray[np.int64]:
    """Stamps (s) as integer microseconds (exact for stamps written as ``%.6f``)."""
    return np.rint(t * 1e6).astype(np.int64)


def _lookup(
    keys: NDArray[np.int64],
    first: NDArray[np.intp],
    counts: NDArray[np.intp],
    k: NDArray[np.int64],
) -> tuple[NDArray[np.intp], NDArray[np.bool_], NDArray[np.bool_]]:
    """First scan index (0 where not found), found, and stamp shared by several scans."""
    if len(keys) == 0:
        none = np.zeros(len(k), dtype=bool)
        return np.zeros(len(k), dtype=np.intp), none, none
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    hit = keys[pos] == k
    return np.where(hit, first[pos], 0), hit, hit & (counts[pos] > 1)


def _match_stamps(
    t: NDArray[np.float64],
    relations: Relations,
    k1: NDArray[np.int64],
    k2: NDArray[np.int64],
    selected: NDArray[np.bool_],
    n_selected: int,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_], int]:
    """The scans of the relations' stamps (``k1``, ``k2`` in microseconds).

    Returns:
        The first scan of each end ``(i1, i2)``, the selected relations whose stamps both
        match, and how many touch a stamp shared by several scans.

    Raises:
        InputError: No relation's stamps match.
    """
    keys, first, counts = np.unique(_micros(t), return_index=True, return_counts=True)
    i1, found1, amb1 = _lookup(keys, first, counts, k1)
    i2, found2, amb2 = _lookup(keys, first, counts, k2)
    found = selected & found1 & found2
    n_ambiguous = int((selected & (amb1 | amb2)).sum())
    n_stamp_missing = n_selected - int(found.sum())
    if n_stamp_missing:
        miss = np.flatnonzero(selected & ~(found1 & found2))[0]
        logger.warning(
            "%s: %d of %d relations have a stamp that matches no scan stamp (first: relation "
            "%d, t1=%.6f t2=%.6f)",
            relations.path,
            n_stamp_missing,
            n_selected,
            int(miss) + 1,
            relations.t1[miss],
            relations.t2[miss],
        )
    if n_ambiguous:
        logger.warning(
            "%s: %d relations touch a stamp shared by several scans; the first scan was used",
            relations.path,
            n_ambiguous,
        )
    if not found.any():
        first_scan = f"{t[0]:.6f}" if len(t) else "none (no scans)"
        raise InputError(
            relations.path,
            "no relation stamps match the scan stamps (first relation stamp "
            f"{relations.t1[0]:.6f} vs first scan stamp {first_scan})",
        )
    return i1, i2, found, n_ambiguous


def _usable(
    p: NDArray[np.float64],
    relations: Relations,
    i1: NDArray[np.intp],
    i2: NDArray[np.intp],
    found: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """The ``found`` relations whose two estimated poses are finite (`InputError`: none)."""
    finite: NDArray[np.bool_] = np.asarray(np.isfinite(p).all(axis=1))
    use = found & finite[i1] & finite[i2]
    n_nan = int(found.sum() - use.sum())
    if n_nan:
        logger.warning(
            "%s: %d relations touch a non-finite estimated pose; counted as unmatched",
            relations.path,
            n_nan,
        )
    if not use.any():
        raise InputError(
            relations.path,
            f"all {int(found.sum())} relations whose stamps match touch a non-finite pose",
        )
    return use


def relation_errors(
    stamps: ArrayLike,
    poses: ArrayLike,
    relations: Relations,
    *,
    max_dt: float | None = None,
) -> RelationErrors:
    """Errors of estimated robot poses against reference relations (Kümmerle et al. 2009).

    Each relation ``(t1, t2, δ*)`` is matched to the scans whose stamps equal ``t1`` and
    ``t2`` exactly, in integer microseconds. A stamp that occurs for several scans takes the
    first of them in file order. With ``x1``, ``x2`` the estimated poses there, the estimated
    relation is ``δ = x1⁻¹ ⊕ x2`` and the error ``ε = δ ⊖ δ* = δ*⁻¹ ⊕ δ``; the translational
    error is ``hypot(εx, εy)``, the rotational one ``|wrap(εθ)|``. The metric does not depend
    on the frame the trajectory is expressed in.

    Args:
        stamps: Scan stamps (s), ``(N,)``, in file order.
        poses: Estimated robot poses ``(N, 3)`` at those stamps; relations touching a
            non-finite pose are counted as unmatched.
        relations: The reference relations (`scanguard.io.relations.read_relations`).
        max_dt: Use only relations with ``|t2 - t1| <= max_dt`` (s); None: all of them.

    Returns:
        The error statistics (means and population standard deviations).

    Raises:
        ValueError: ``stamps`` and ``poses`` disagree in length, or ``max_dt`` is negative.
        InputError: No relation can be used (names the relations file).
    """
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = as_pose(poses).reshape(-1, 3)
    if t.shape[0] != p.shape[0]:
        raise ValueError(f"{t.shape[0]} stamps but {p.shape[0]} poses")
    if max_dt is not None and not max_dt >= 0.0:
        raise ValueError(f"max_dt must be a non-negative number of seconds, got {max_dt}")
    n_rel = len(relations.t1)
    k1, k2 = _micros(relations.t1), _micros(relations.t2)
    selected = np.ones(n_rel, dtype=bool)
    if max_dt is not None:
        selected = np.abs(k2 - k1) <= int(np.rint(max_dt * 1e6))
    n_selected = int(selected.sum())
    if n_selected == 0:
        raise InputError(
            relations.path, f"none of the {n_rel} relations spans at most {max_dt:g} s"
        )

    i1, i2, found, n_ambiguous = _match_stamps(t, relations, k1, k2, selected, n_selected)
    use = _usable(p, relations, i1, i2, found)
    estimated = relative(p[i1[use]], p[i2[use]])
    eps = relative(relations.delta[use], estimated)
    trans = np.hypot(eps[:, 0], eps[:, 1])
    rot = np.degrees(np.abs(wrap_angle(eps[:, 2])))
    n_used = int(use.sum())
    return RelationErrors(
        n_relations=n_rel,
        n_matched=n_used,
        n_unmatched=n_selected - n_used,
        n_ambiguous_stamps=n_ambiguous,
        trans_mean=float(trans.mean()),
        trans_std=float(trans.std()),
        trans_sq_mean=float((trans**2).mean()),
        trans_sq_std=float((trans**2).std()),
        rot_mean_deg=float(rot.mean()),
        rot_std_deg=float(rot.std()),
        rot_sq_mean=float((rot**2).mean()),
        rot_sq_std=float((rot**2).std()),
        max_dt=None if max_dt is None else float(max_dt),
    )


def _pm(mean: float, std: float, digits: int) -> str:
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def relation_table_markdown(
    results: Mapping[str, RelationErrors],
    published: Mapping[str, tuple[float, float]] | None = None,
) -> str:
    """A Markdown table of relation errors, one row per trajectory.

    Args:
        results: Trajectory name -> its errors (`relation_errors`).
        published: Method name -> (mean, std) of the absolute translational error (m) of
            published results (e.g. from `published_for`); appended as rows marked
            "(published)" with the other columns empty.

    Returns:
        The table (header, separator, rows), ending in a newline.
    """
    lines = [
        "| trajectory | relations used | trans. abs. (m) | trans. sq. (m²) "
        "| rot. abs. (deg) | rot. sq. (deg²) |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        used = f"{r.n_matched}/{r.n_selected}"
        if r.max_dt is not None:
            used += f" (Δt ≤ {r.max_dt:g} s, of {r.n_relations})"
        cells = [
            _escape(name),
            used,
            _pm(r.trans_mean, r.trans_std, 3),
            _pm(r.trans_sq_mean, r.trans_sq_std, 3),
            _pm(r.rot_mean_deg, r.rot_std_deg, 2),
            _pm(r.rot_sq_mean, r.rot_sq_std, 2),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    for name, (mean, std) in (published or {}).items():
        cells = [f"{_escape(name)} (published)", "", _pm(mean, std, 3), "", "", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _escape(text: str) -> str:
    """Escape the Markdown table separator in a cell."""
    return text.replace("|", "\\|")
