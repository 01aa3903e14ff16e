"""The relations of a run: found next to the recording, checked before the loop, scored after.

Kümmerle et al.'s reference relations (``RunConfig.relations``, else `find_relations`) are
read once; `check_relations` refuses, before any work, a file of which fewer than
`scanguard.slam.relations.MIN_RELATION_COVERAGE` of the relations inside the recording find
their scans; `score_relations` scores every trajectory on all relations and on those spanning
at most ``relations_short_dt`` seconds.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.run_result import ResolvedRun, RunResult
from scanguard.errors import InputError

logger = logging.getLogger(__name__)

#: Recording suffixes next to which `find_relations` looks for ``<stem>.relations``.
RELATION_RECORDING_SUFFIXES = (".clf.gz", ".clf", ".log.gz", ".log")


def find_relations(recording: str | Path) -> Path | None:
    """The ``<stem>.relations`` file next to a CARMEN recording, if there is one.

    ``intel.clf.gz``, ``intel.clf`` and ``intel.log`` all look for ``intel.relations`` in the
    same folder.

    Args:
        recording: Path of the recording.

    Returns:
        The relations file, or None (other formats, no such file, or a name that no file
        can have: ``<251 characters>.relations`` is longer than a file name may be).
    """
    p = Path(recording)
    name = p.name
    for suffix in RELATION_RECORDING_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            candidate = p.with_name(name[: -len(suffix)] + ".relations")
            try:
                return candidate if candidate.is_file() else None
            except OSError:  # a name that cannot exist (too long for the file system)
                return None
    return None


def check_relations(
    relations: Any, stamps: NDArray[np.float64], tolerance: float, *, cut: bool = False
) -> str | None:
    """Refuse before the run (not after it) a relations file whose stamps miss the scans.

    Every relation inside the recording's time span must find its two scans (nearest stamp
    within ``tolerance``); below `MIN_RELATION_COVERAGE` of them the figures would describe
    a few relations only, which a user would publish as the log's error. A recording ``cut``
    so short (``--max-scans``) that every relation lies after its end is not refused: the
    run goes on without the relation metric. Uncut, such a file is refused: the whole
    recording holds none of its relations (another recording's file, or another clock).

    Returns:
        None when the relations can be scored, else the note saying why they are not.

    Raises:
        InputError: Relations lie inside the recording, but too few find their scans.
    """
    from scanguard.slam.relations import MIN_RELATION_COVERAGE, relation_errors

    lo, hi = float(stamps.min()) - tolerance, float(stamps.max()) + tolerance
    ends = np.stack([relations.t1, relations.t2])
    if cut and not ((ends >= lo) & (ends <= hi)).all(axis=0).any() and ends.max() > hi:
        return (
            f"not scored: none of the {ends.shape[1]} relations of {relations.path} lies inside "
            f"the recording (scans {stamps.min():.3f}..{stamps.max():.3f} s, relations "
            f"{ends.min():.3f}..{ends.max():.3f} s; a recording cut short, e.g. by --max-scans)"
        )
    r = relation_errors(stamps, np.zeros((len(stamps), 3)), relations, tolerance=tolerance)
    if r.partial:
        raise InputError(
            relations.path,
            f"only {r.n_matched} of the {r.n_selected - r.n_outside} relations inside the "
            f"recording have scan stamps within {tolerance:g} s ({100 * r.coverage:.1f} %, "
            f"below {100 * MIN_RELATION_COVERAGE:.0f} %): wrong relations file, or stamps on "
            "another clock (see --relation-tolerance)",
        )
    return None


def score_relations(res: RunResult, run: ResolvedRun, trajs: dict[str, Any]) -> None:
    """Relation errors of every trajectory: all relations, and the short ones.

    Never raises over a figure: the run is done, and a figure that cannot be computed (e.g.
    a trajectory whose poses are all non-finite where the relations are) is left out with a
    warning and a note (``res.relations_note``), the rest of the result kept.
    """
    from scanguard.slam.relations import relation_errors

    stamps, relations = run.seq.stamps, run.relations
    short, tol = run.cfg.relations_short_dt, run.cfg.relation_tolerance
    missing: dict[str, list[str]] = {}  # "<scope>: <problem>" -> trajectories
    for scope, max_dt in (("all", None), (f"dt <= {short:g} s", short)):
        table: dict[str, Any] = {}
        for name, t in trajs.items():
            try:
                table[name] = relation_errors(stamps, t, relations, max_dt=max_dt, tolerance=tol)
            except InputError as exc:
                missing.setdefault(f"{scope}: {exc.problem}", []).append(name)
        if table:
            res.relations[scope] = table
    notes = [f"{why} ({', '.join(names)})" for why, names in missing.items()]
    for note in notes:
        logger.warning("relations not scored: %s", note)
    if notes:
        res.relations_note = "not scored: " + "; ".join(notes)
