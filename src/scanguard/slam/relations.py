"""The Kümmerle et al. 2009 relation metric: a trajectory scored against reference relations.

`relation_errors` matches every relation stamp to the nearest scan stamp within a tolerance
(default `RELATION_TOLERANCE`, 1 ms), so relations files printed with any number of decimals
score the same trajectory alike; a figure that uses fewer than `MIN_RELATION_COVERAGE` of the
relations inside the recording is `RelationErrors.partial`, and every table marks it.
`PUBLISHED_RELATION_ERRORS` holds the paper's Table 1 for the three Freiburg logs.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import InputError
from scanguard.geometry import as_pose, relative, wrap_angle

if TYPE_CHECKING:
    from scanguard.io.relations import Relations

logger = logging.getLogger(__name__)

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


#: Default tolerance (s) of the nearest-stamp matching of relation stamps to scan stamps.
RELATION_TOLERANCE = 1e-3
#: A relation figure on fewer than this fraction of the relations it could use is partial.
MIN_RELATION_COVERAGE = 0.95


@dataclass(frozen=True)
class RelationErrors:
    """Errors of a trajectory against reference relations (Kümmerle et al. 2009).

    ``n_matched + n_unmatched`` relations passed the ``max_dt`` filter (all of them without
    one); the other ``n_relations - n_matched - n_unmatched`` were left out by it.

    Attributes:
        n_relations: Relations in the file.
        n_matched: Relations used: both stamps found among the scan stamps, finite poses.
        n_unmatched: Relations within ``max_dt`` that could not be used (a stamp with no scan
            stamp within ``tolerance``, or a non-finite estimated pose).
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
        tolerance: A relation stamp takes the nearest scan stamp within this many seconds.
        n_collapsed_stamps: Distinct relation stamps that fell on the same scan as another
            distinct relation stamp (the tolerance is wider than the scan spacing there).
        n_outside: Relations within ``max_dt`` with a stamp outside the recording's time span
            (before its first or after its last scan, beyond ``tolerance``): a recording cut
            short (``--max-scans``) leaves these out; they are among ``n_unmatched``.
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
    tolerance: float = RELATION_TOLERANCE
    n_collapsed_stamps: int = 0
    n_outside: int = 0

    @property
    def n_selected(self) -> int:
        """Relations that passed the ``max_dt`` filter (matched or not)."""
        return self.n_matched + self.n_unmatched

    @property
    def coverage(self) -> float:
        """Fraction of the relations inside the recording's span that the figure uses."""
        inside = self.n_selected - self.n_outside
        return self.n_matched / inside if inside > 0 else 0.0

    @property
    def partial(self) -> bool:
        """The figure uses fewer than `MIN_RELATION_COVERAGE` of the relations it could."""
        return self.coverage < MIN_RELATION_COVERAGE

    def used_text(self) -> str:
        """``"1172 of 1172"``, with the share and "PARTIAL" when the figure is partial."""
        text = f"{self.n_matched} of {self.n_selected}"
        if self.n_outside:
            text += f" ({self.n_outside} outside the recording)"
        if self.partial:
            text += f" PARTIAL ({100 * self.coverage:.0f} %)"
        return text

    def as_dict(self) -> dict[str, float | int | bool | None]:
        """Plain dict (for JSON/CSV), with ``coverage`` and ``partial``."""
        out: dict[str, float | int | bool | None] = dict(asdict(self))
        out["coverage"] = self.coverage
        out["partial"] = self.partial
        return out


def _micros(t: NDArray[np.float64]) -> NDArray[np.int64]:
    """Stamps (s) as integer microseconds (for the ``max_dt`` filter)."""
    return np.rint(t * 1e6).astype(np.int64)


@dataclass(frozen=True)
class _StampIndex:
    """Sorted distinct scan stamps, the first scan of each, and how many scans share it."""

    keys: NDArray[np.float64]
    first: NDArray[np.intp]
    counts: NDArray[np.intp]

    @classmethod
    def of(cls, stamps: NDArray[np.float64]) -> _StampIndex:
        keys, first, counts = np.unique(stamps, return_index=True, return_counts=True)
        return cls(keys, first, counts)

    def nearest(
        self, query: NDArray[np.float64], tolerance: float
    ) -> tuple[NDArray[np.intp], NDArray[np.bool_], NDArray[np.bool_]]:
        """The nearest scan stamp of each query within ``tolerance``.

        Returns:
            First scan of the nearest stamp (0 where none is within ``tolerance``), found, and
            stamp shared by several scans.
        """
        n = len(query)
        if len(self.keys) == 0:
            none = np.zeros(n, dtype=bool)
            return np.zeros(n, dtype=np.intp), none, none
        hi = np.clip(np.searchsorted(self.keys, query), 0, len(self.keys) - 1)
        lo = np.maximum(hi - 1, 0)
        # the nearer neighbour; on a tie the earlier stamp (stable: the left one)
        pick = np.where(np.abs(self.keys[lo] - query) <= np.abs(self.keys[hi] - query), lo, hi)
        # float stamps of ~1e9 s carry ~1e-7 s of rounding: never let it decide
        hit = np.abs(self.keys[pick] - query) <= tolerance + 1e-9
        return np.where(hit, self.first[pick], 0), hit, hit & (self.counts[pick] > 1)


def _collapsed(stamps: NDArray[np.float64], index: NDArray[np.intp], hit: NDArray[np.bool_]) -> int:
    """Distinct relation stamps that share their scan with another distinct relation stamp."""
    values, pos = np.unique(stamps[hit], return_index=True)
    scans = index[hit][pos]
    _, per_scan = np.unique(scans, return_counts=True)
    return int(per_scan[per_scan > 1].sum()) if len(values) else 0


def _match_stamps(
    t: NDArray[np.float64],
    relations: Relations,
    selected: NDArray[np.bool_],
    tolerance: float,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_], dict[str, int]]:
    """The scans of the relations' stamps: the nearest scan stamp within ``tolerance``.

    Returns:
        The first scan of each end ``(i1, i2)``, the selected relations whose stamps both
        match, and the counts ``ambiguous``, ``collapsed`` and ``outside``.

    Raises:
        InputError: No relation's stamps match.
    """
    idx = _StampIndex.of(t)
    i1, found1, amb1 = idx.nearest(relations.t1, tolerance)
    i2, found2, amb2 = idx.nearest(relations.t2, tolerance)
    found = selected & found1 & found2
    counts = {"ambiguous": int((selected & (amb1 | amb2)).sum()), "collapsed": 0, "outside": 0}
    if len(t):
        lo, hi = float(t.min()) - tolerance, float(t.max()) + tolerance
        ends = np.stack([relations.t1, relations.t2])
        counts["outside"] = int((selected & ((ends < lo) | (ends > hi)).any(axis=0)).sum())
        both = np.concatenate([relations.t1[selected], relations.t2[selected]])
        both_i = np.concatenate([i1[selected], i2[selected]])
        both_hit = np.concatenate([found1[selected], found2[selected]])
        counts["collapsed"] = _collapsed(both, both_i, both_hit)
    _warn_matching(relations, t, selected, found, found1 & found2, counts, tolerance)
    return i1, i2, found, counts


def _warn_matching(
    relations: Relations,
    t: NDArray[np.float64],
    selected: NDArray[np.bool_],
    found: NDArray[np.bool_],
    both: NDArray[np.bool_],
    counts: dict[str, int],
    tolerance: float,
) -> None:
    """Log what the stamp matching could not do cleanly; refuse when nothing matched."""
    n_selected = int(selected.sum())
    n_missing = n_selected - int(found.sum())
    if n_missing:
        miss = np.flatnonzero(selected & ~both)[0]
        logger.warning(
            "%s: %d of %d relations have a stamp with no scan stamp within %g s (%d outside "
            "the recording; first: relation %d, t1=%.6f t2=%.6f)",
            relations.path,
            n_missing,
            n_selected,
            tolerance,
            counts["outside"],
            int(miss) + 1,
            relations.t1[miss],
            relations.t2[miss],
        )
    if counts["ambiguous"]:
        logger.warning(
            "%s: %d relations touch a stamp shared by several scans; the first scan was used",
            relations.path,
            counts["ambiguous"],
        )
    if counts["collapsed"]:
        logger.warning(
            "%s: %d distinct relation stamps fall on a scan shared with another relation stamp "
            "(tolerance %g s is wider than the scan spacing there)",
            relations.path,
            counts["collapsed"],
            tolerance,
        )
    if not found.any():
        first_scan = f"{t[0]:.6f}" if len(t) else "none (no scans)"
        raise InputError(
            relations.path,
            f"no relation stamps match the scan stamps within {tolerance:g} s (first relation "
            f"stamp {relations.t1[0]:.6f} vs first scan stamp {first_scan})",
        )


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
    tolerance: float = RELATION_TOLERANCE,
) -> RelationErrors:
    """Errors of estimated robot poses against reference relations (Kümmerle et al. 2009).

    Each relation ``(t1, t2, δ*)`` is matched to the scans whose stamps are nearest to ``t1``
    and ``t2``, if within ``tolerance`` seconds (so relations printed with 3, 5, 6 or 9
    decimals all find their scans). A stamp that occurs for several scans takes the first of
    them in file order. With ``x1``, ``x2`` the estimated poses there, the estimated relation
    is ``δ = x1⁻¹ ⊕ x2`` and the error ``ε = δ ⊖ δ* = δ*⁻¹ ⊕ δ``; the translational error is
    ``hypot(εx, εy)``, the rotational one ``|wrap(εθ)|``. The metric does not depend on the
    frame the trajectory is expressed in.

    Args:
        stamps: Scan stamps (s), ``(N,)``, in file order.
        poses: Estimated robot poses ``(N, 3)`` at those stamps; relations touching a
            non-finite pose are counted as unmatched.
        relations: The reference relations (`scanguard.io.relations.read_relations`).
        max_dt: Use only relations with ``|t2 - t1| <= max_dt`` (s); None: all of them.
        tolerance: Largest distance (s) between a relation stamp and its scan stamp (0:
            exact to the float).

    Returns:
        The error statistics (means and population standard deviations), with how many
        relations were used (`RelationErrors.coverage`, `RelationErrors.partial`).

    Raises:
        ValueError: ``stamps`` and ``poses`` disagree in length, ``max_dt`` or ``tolerance``
            is negative.
        InputError: No relation can be used (names the relations file).
    """
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = as_pose(poses).reshape(-1, 3)
    if t.shape[0] != p.shape[0]:
        raise ValueError(f"{t.shape[0]} stamps but {p.shape[0]} poses")
    if max_dt is not None and not max_dt >= 0.0:
        raise ValueError(f"max_dt must be a non-negative number of seconds, got {max_dt}")
    if not tolerance >= 0.0:
        raise ValueError(f"tolerance must be a non-negative number of seconds, got {tolerance}")
    n_rel = len(relations.t1)
    selected = np.ones(n_rel, dtype=bool)
    if max_dt is not None:
        k1, k2 = _micros(relations.t1), _micros(relations.t2)
        selected = np.abs(k2 - k1) <= int(np.rint(max_dt * 1e6))
    if not selected.any():
        raise InputError(
            relations.path, f"none of the {n_rel} relations spans at most {max_dt:g} s"
        )
    i1, i2, found, counts = _match_stamps(t, relations, selected, tolerance)
    use = _usable(p, relations, i1, i2, found)
    return _statistics(p, relations, i1, i2, use, selected, counts, max_dt, tolerance)


def _statistics(
    p: NDArray[np.float64],
    relations: Relations,
    i1: NDArray[np.intp],
    i2: NDArray[np.intp],
    use: NDArray[np.bool_],
    selected: NDArray[np.bool_],
    counts: dict[str, int],
    max_dt: float | None,
    tolerance: float,
) -> RelationErrors:
    """The error statistics of the ``use``d relations."""
    estimated = relative(p[i1[use]], p[i2[use]])
    eps = relative(relations.delta[use], estimated)
    trans = np.hypot(eps[:, 0], eps[:, 1])
    rot = np.degrees(np.abs(wrap_angle(eps[:, 2])))
    n_used = int(use.sum())
    return RelationErrors(
        n_relations=len(relations.t1),
        n_matched=n_used,
        n_unmatched=int(selected.sum()) - n_used,
        n_ambiguous_stamps=counts["ambiguous"],
        trans_mean=float(trans.mean()),
        trans_std=float(trans.std()),
        trans_sq_mean=float((trans**2).mean()),
        trans_sq_std=float((trans**2).std()),
        rot_mean_deg=float(rot.mean()),
        rot_std_deg=float(rot.std()),
        rot_sq_mean=float((rot**2).mean()),
        rot_sq_std=float((rot**2).std()),
        max_dt=None if max_dt is None else float(max_dt),
        tolerance=float(tolerance),
        n_collapsed_stamps=counts["collapsed"],
        n_outside=counts["outside"],
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
        used = r.used_text()
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
