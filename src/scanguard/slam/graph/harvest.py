"""Labelled loop-closure candidates from simulation: the training data of the closure judge.

`harvest_candidates` runs the ``graph`` back end over a sequence with the reference
(oracle) judge, so that wrong closures never corrupt the graph and every later candidate is
proposed from a correct map, and returns every candidate it proposed with its reference
label (`scanguard.slam.graph.closure.closure_label`).

`candidate_table` turns the records into feature columns (`FEATURES`), all of them available
to a judge at run time (never errors or labels):

* the loop matcher's ``response`` and ``coarse_response``;
* the response-surface standard deviations ``std_x``, ``std_y``, ``std_theta`` and
  ``std_xy = max(std_x, std_y)``;
* how far the closure would move the graph: ``disagreement_m`` / ``disagreement_rad`` (the
  proposed against the graph's prior relative pose), the same per metre of ``path_gap``
  (``disagreement_m_per_m``, ``disagreement_rad_per_m``; drift grows with the path), and the
  ``path_gap`` itself;
* the ICP quality metrics of the ``icp-paper`` matcher run on the pair (current scan onto the
  target node's scan) from the proposed pose, prefixed ``icp_`` (`ICP_METRICS`), plus
  ``icp_shift_m`` / ``icp_shift_rad``: how far that ICP moves away from the proposed pose;
* optionally ``cnn_proba``: the shipped sequential-pair detector's fault probability.

`harvest_table` runs several scenarios x seeds and caches the table in an ``.npz`` (atomic
writes, resumable per (scenario, seed)).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.detect.baselines.base import LEGACY_METRICS_FEATURES
from scanguard.errors import FormatError
from scanguard.fsutil import atomic_path
from scanguard.geometry import as_pose, compose, relative, wrap_angle
from scanguard.pairs.labels import AMBIGUOUS
from scanguard.slam.graph.closure import ClosureRecord, ReferenceClosureJudge
from scanguard.slam.graph.config import GraphConfig

logger = logging.getLogger(__name__)

ICP_MATCHER = "icp-paper"
"""Matcher whose quality metrics describe a candidate pair (the shipped detector's)."""

ICP_METRICS: tuple[str, ...] = tuple(
    k for k in LEGACY_METRICS_FEATURES if k not in ("translation", "rotation")
)
"""Keys of `scanguard.matching.MatchResult.metrics` kept (prefixed ``icp_``)."""

CANDIDATE_FEATURES: tuple[str, ...] = (
    "response",
    "coarse_response",
    "std_x",
    "std_y",
    "std_theta",
    "std_xy",
    "disagreement_m",
    "disagreement_rad",
    "disagreement_m_per_m",
    "disagreement_rad_per_m",
    "path_gap",
)
"""Features read from the candidate itself (matcher outputs and graph geometry)."""

FEATURES: tuple[str, ...] = (
    CANDIDATE_FEATURES + tuple(f"icp_{k}" for k in ICP_METRICS) + ("icp_shift_m", "icp_shift_rad")
)
"""Every feature column of `candidate_table` (plus ``cnn_proba`` when a detector is given)."""

_GAP_FLOOR = 1.0  # m: the per-metre disagreements of short loops are not blown up


#: Judges of the harvest runs: ``oracle`` (only correct closures enter the graph: the
#: candidates a well-guarded graph sees) and ``none`` (every candidate enters: a drifted or
#: folded graph, where a wrong closure can agree with a wrong estimate). A judge trained on the
#: first alone learns to trust "how far the closure moves the graph" too much.
HARVEST_JUDGES = ("oracle", "none")


def harvest_candidates(
    seq: Any, config: GraphConfig | None = None, *, judge: str = "oracle"
) -> list[ClosureRecord]:
    """Every loop-closure candidate of a run of the graph over ``seq``, with its label.

    Args:
        seq: A `scanguard.sim.ScanSequence` (or anything with ``scans``, ``odometry``,
            ``reference``, ``laser_offset`` and ``sensor.range_max``).
        config: Graph settings (defaults if None).
        judge: Who decides during the harvest run (see `HARVEST_JUDGES`); labels always come
            from the reference.

    Returns:
        The back end's `ClosureRecord` list (candidates keep their scans).
    """
    from scanguard.slam.graph.backend import GraphBackend
    from scanguard.slam.graph.closure import AcceptAll

    cfg = config or GraphConfig()
    reference = as_pose(seq.reference).reshape(-1, 3)
    if judge not in HARVEST_JUDGES:
        raise ValueError(f"harvest judge {judge!r}: use one of {', '.join(HARVEST_JUDGES)}")
    judge_fn: Any = (
        ReferenceClosureJudge(compose(reference, seq.laser_offset), cfg.closures.labels)
        if judge == "oracle"
        else AcceptAll()
    )
    backend = GraphBackend(
        cfg,
        laser_offset=seq.laser_offset,
        initial_pose=reference[0],
        range_max=float(seq.sensor.range_max),
        closure_judge=judge_fn,
        reference=reference,
    )
    odometry = None if seq.odometry is None else np.asarray(seq.odometry, dtype=np.float64)
    for i, scan in enumerate(seq.scans):
        backend.update(scan, None if odometry is None else odometry[i])
    return list(backend.closures)


def icp_features(record_or_candidate: Any, matcher: Any = None) -> dict[str, float]:
    """The ``icp_*`` features of one candidate (NaN when its scans are gone).

    Args:
        record_or_candidate: A `ClosureRecord` or a `ClosureCandidate`.
        matcher: Matcher to run (None = `ICP_MATCHER`).
    """
    from scanguard.matching import get_matcher

    cand = getattr(record_or_candidate, "candidate", record_or_candidate)
    names = [f"icp_{k}" for k in ICP_METRICS] + ["icp_shift_m", "icp_shift_rad"]
    if getattr(cand, "source", None) is None or getattr(cand, "target", None) is None:
        return dict.fromkeys(names, math.nan)
    matcher = matcher or get_matcher(ICP_MATCHER)
    pose = np.asarray(cand.pose, dtype=np.float64)
    m = matcher(cand.source.points(np.float64), cand.target.points(np.float64), pose)
    metrics = m.metrics()
    out = {f"icp_{k}": float(metrics.get(k, math.nan)) for k in ICP_METRICS}
    shift = relative(as_pose(pose), as_pose(np.asarray(m.pose, dtype=np.float64)))
    out["icp_shift_m"] = float(math.hypot(shift[0], shift[1]))
    out["icp_shift_rad"] = float(abs(wrap_angle(shift[2])))
    return out


def candidate_features(record_or_candidate: Any, matcher: Any = None) -> dict[str, float]:
    """All `FEATURES` of one candidate (a `ClosureRecord` or a `ClosureCandidate`)."""
    cand = getattr(record_or_candidate, "candidate", record_or_candidate)
    s = cand.std
    dm, dr = cand.disagreement
    gap = float(cand.path_gap)
    norm = max(gap, _GAP_FLOOR) if math.isfinite(gap) else math.nan
    out = {
        "response": float(cand.score),
        "coarse_response": float(cand.coarse_score),
        "std_x": float(s[0]),
        "std_y": float(s[1]),
        "std_theta": float(s[2]),
        "std_xy": float(max(s[0], s[1])),
        "disagreement_m": dm,
        "disagreement_rad": dr,
        "disagreement_m_per_m": dm / norm,
        "disagreement_rad_per_m": dr / norm,
        "path_gap": gap,
    }
    out.update(icp_features(cand, matcher))
    return out


def cnn_probability(detector: Any, record_or_candidate: Any) -> float:
    """The shipped detector's fault probability on a candidate (as `DetectorClosureJudge`)."""
    from scanguard.slam.graph.closure import DetectorClosureJudge

    cand = getattr(record_or_candidate, "candidate", record_or_candidate)
    if getattr(cand, "source", None) is None:
        return math.nan
    return DetectorClosureJudge(detector).probability(cand)


def candidate_table(
    records: Sequence[ClosureRecord], detector: Any = None
) -> dict[str, NDArray[np.float64]]:
    """Feature columns of candidates, plus their labels and reference errors.

    Args:
        records: Closure records (`harvest_candidates`).
        detector: When given, a ``cnn_proba`` column with its fault probability.

    Returns:
        ``{name: (N,)}``: every name of `FEATURES` (and ``cnn_proba``), ``label`` (0 normal,
        1 fault, -1 ambiguous: drop those for fitting), ``trans_error`` and ``rot_error``.
    """
    from scanguard.matching import get_matcher

    matcher = get_matcher(ICP_MATCHER)
    names = list(FEATURES) + (["cnn_proba"] if detector is not None else [])
    cols: dict[str, list[float]] = {n: [] for n in names}
    for extra in ("label", "trans_error", "rot_error"):
        cols[extra] = []
    for rec in records:
        feats = candidate_features(rec, matcher)
        if detector is not None:
            feats["cnn_proba"] = cnn_probability(detector, rec)
        for n in names:
            cols[n].append(feats[n])
        cols["label"].append(float(getattr(rec, "label", AMBIGUOUS)))
        cols["trans_error"].append(float(getattr(rec, "trans_error", math.nan)))
        cols["rot_error"].append(float(getattr(rec, "rot_error", math.nan)))
    return {k: np.asarray(v, dtype=np.float64) for k, v in cols.items()}


def labelled(table: dict[str, NDArray[Any]]) -> dict[str, NDArray[Any]]:
    """The rows of ``table`` whose label is normal or fault (ambiguous ones dropped)."""
    keep = np.asarray(table["label"]) >= 0
    return {k: np.asarray(v)[keep] for k, v in table.items()}


def select(table: dict[str, NDArray[Any]], mask: NDArray[np.bool_]) -> dict[str, NDArray[Any]]:
    """The rows of ``table`` where ``mask`` holds."""
    return {k: np.asarray(v)[mask] for k, v in table.items()}


def concat(tables: Iterable[dict[str, NDArray[Any]]]) -> dict[str, NDArray[Any]]:
    """Row-wise concatenation of tables with the same columns (empty dict for none)."""
    items = [t for t in tables if t]
    if not items:
        return {}
    keys = list(items[0])
    return {k: np.concatenate([np.asarray(t[k]) for t in items]) for k in keys}


def load_table(path: str | Path) -> dict[str, NDArray[Any]]:
    """The candidate rows of a cached harvest (`harvest_table`).

    Raises:
        FormatError: The file is not a harvest cache.
    """
    return _load_cache(path)[0]


def _load_cache(path: str | Path) -> tuple[dict[str, NDArray[Any]], set[tuple[str, int]]]:
    """Rows and finished (scenario, seed) pairs of a harvest cache."""
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as data:
            table = {k: np.asarray(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise FormatError(p, f"not a closure-candidate cache ({exc})") from None
    for key in ("done_scenario", "done_seed"):
        if key not in table:
            raise FormatError(p, f"not a closure-candidate cache (no {key!r} column)")
    names, seeds = table.pop("done_scenario"), table.pop("done_seed")
    if table and not {"label", "scenario", "seed"} <= table.keys():
        raise FormatError(p, "not a closure-candidate cache (no label / scenario / seed)")
    done = {(str(n), int(s)) for n, s in zip(names, seeds, strict=True)}
    return table, done


def _save_cache(
    path: str | Path, table: dict[str, NDArray[Any]], done: set[tuple[str, int]]
) -> None:
    pairs = sorted(done)
    save_table(
        path,
        {
            **table,
            "done_scenario": np.array([q[0] for q in pairs], dtype="U32"),
            "done_seed": np.array([q[1] for q in pairs], dtype=np.int64),
        },
    )


def merge_caches(parts: Sequence[str | Path], dest: str | Path) -> None:
    """Merge harvest caches (of disjoint scenario / seed pairs) into ``dest``."""
    tables, done = [], set()
    for part in parts:
        if Path(part).is_file():
            t, d = _load_cache(part)
            tables.append(t)
            done |= d
    _save_cache(dest, concat(tables), done)


def save_table(path: str | Path, table: dict[str, NDArray[Any]]) -> None:
    """Write a table atomically as ``.npz``."""
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        arrays: dict[str, Any] = {k: np.asarray(v) for k, v in table.items()}
        np.savez_compressed(fh, **arrays)


def harvest_table(
    scenarios: Sequence[str],
    seeds: Sequence[int],
    *,
    cache: str | Path | None = None,
    detector: Any = None,
    config: GraphConfig | None = None,
    simulate_fn: Callable[..., Any] | None = None,
) -> dict[str, NDArray[Any]]:
    """Harvest and tabulate candidates of ``scenarios`` x ``seeds``, with a resumable cache.

    Each finished (scenario, seed) is appended to ``cache`` at once (atomic rewrite); a rerun
    skips the ones already there. A (scenario, seed) with no candidate is remembered too.

    Args:
        scenarios: Simulated scenario names (`scanguard.sim.simulate`).
        seeds: Seeds of each scenario.
        cache: ``.npz`` cache (None = no cache).
        detector: Passed to `candidate_table` (a ``cnn_proba`` column).
        config: Graph settings.
        simulate_fn: ``simulate(name, seed=...)`` (None = `scanguard.sim.simulate`).

    Returns:
        The table of the requested (scenario, seed) pairs, with ``scenario`` (str) and ``seed``
        (int) columns, ambiguous rows included.
    """
    if simulate_fn is None:
        from scanguard.sim import simulate

        simulate_fn = simulate
    table: dict[str, NDArray[Any]] = {}
    done: set[tuple[str, int]] = set()
    if cache is not None and Path(cache).is_file():
        table, done = _load_cache(cache)
    for name in scenarios:
        for seed in seeds:
            if (name, int(seed)) in done:
                continue
            seq = simulate_fn(name, seed=int(seed))
            parts = []
            for hj in HARVEST_JUDGES:
                records = harvest_candidates(seq, config, judge=hj)
                t: dict[str, NDArray[Any]] = dict(candidate_table(records, detector))
                t["harvest"] = np.array([hj] * len(records), dtype="U8")
                parts.append(t)
            part = concat(parts)
            n = len(part["label"])
            part["scenario"] = np.array([name] * n, dtype="U32")
            part["seed"] = np.full(n, int(seed), dtype=np.int64)
            labels = part["label"]
            logger.info(
                "%s seed %d: %d candidates (%d normal, %d fault, %d ambiguous)",
                name,
                seed,
                n,
                int((labels == 0).sum()),
                int((labels == 1).sum()),
                int((labels < 0).sum()),
            )
            if n:
                table = concat([table, part]) if table else part
            done.add((name, int(seed)))
            if cache is not None:
                _save_cache(cache, table, done)
    if not table:
        return {}
    want = np.isin(table["scenario"], list(scenarios)) & np.isin(table["seed"], list(seeds))
    return select(table, want)


__all__ = [
    "CANDIDATE_FEATURES",
    "FEATURES",
    "ICP_MATCHER",
    "ICP_METRICS",
    "candidate_features",
    "candidate_table",
    "cnn_probability",
    "concat",
    "harvest_candidates",
    "harvest_table",
    "icp_features",
    "labelled",
    "load_table",
    "merge_caches",
    "save_table",
    "select",
]
