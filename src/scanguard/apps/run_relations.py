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
        The relations file, or None (other formats, or no such file).
    """
    p = Path(recording)
    name = p.name
    for suffix in RELATION_RECORDING_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            candidate = p.with_name(name[: -len(suffix)] + ".relations")
            return candidate if candidate.is_file() else None
    return None


def check_relations(relations: Any, stamps: NDArray[np.float64], tolerance: float) -> None:
    """Refuse before the run (not after it) a relations file whose stamps miss the scans.

    Every relation inside the recording's time span must find its two scans (nearest stamp
    within ``tolerance``); below `MIN_RELATION_COVERAGE` of them the figures would describe
    a few relations only, which a user would publish as the log's error.
    """
    from scanguard.slam.relations import MIN_RELATION_COVERAGE, relation_errors

    r = relation_errors(stamps, np.zeros((len(stamps), 3)), relations, tolerance=tolerance)
    if r.partial:
        raise InputError(
            relations.path,
            f"only {r.n_matched} of the {r.n_selected - r.n_outside} relations inside the "
            f"recording have scan stamps within {tolerance:g} s ({100 * r.coverage:.1f} %, "
            f"below {100 * MIN_RELATION_COVERAGE:.0f} %): wrong relations file, or stamps on "
            "another clock (see --relation-tolerance)",
        )


def score_relations(res: RunResult, run: ResolvedRun, trajs: dict[str, Any]) -> None:
    """Relation errors of every trajectory: all relations, and the short ones."""
    from scanguard.slam.relations import relation_errors

    stamps, relations = run.seq.stamps, run.relations
    short, tol = run.cfg.relations_short_dt, run.cfg.relation_tolerance
    res.relations["all"] = {
        k: relation_errors(stamps, t, relations, tolerance=tol) for k, t in trajs.items()
    }
    try:
        res.relations[f"dt <= {short:g} s"] = {
            k: relation_errors(stamps, t, relations, max_dt=short, tolerance=tol)
            for k, t in trajs.items()
        }
    except InputError as exc:
        logger.warning("no relations spanning at most %g s: %s", short, exc)
