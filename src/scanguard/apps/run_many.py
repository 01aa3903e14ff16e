"""``scanguard run-many``: the guarded SLAM over many recordings, one merged table.

`run_many` runs the guarded SLAM (`scanguard.apps.run.run_recording`, as ``scanguard run``) over
many recordings, one task each, into ``OUT/<recording-stem>/``, resumes finished ones, and writes
one merged results table (``OUT/results.csv`` and ``OUT/results.md``).
"""

from __future__ import annotations

import glob
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scanguard.apps.batch import TABLE_FILES, check_result_names, read_json, resumable, write_table
from scanguard.errors import InputError
from scanguard.runtime.executor import Executor

logger = logging.getLogger(__name__)


_GLOB_CHARS = "*?["


def _extensions() -> list[str]:
    from scanguard.io import READERS

    return sorted((e for e in READERS if e), key=len, reverse=True)


def _is_bag_folder(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def recording_stem(path: str | Path) -> str:
    """The name of a recording without its reader extension (``intel.log.gz`` -> ``intel``)."""
    p = Path(path)
    if p.is_dir():
        return p.name
    name = p.name
    for ext in _extensions():
        if name.lower().endswith(ext):
            return name[: -len(ext)]
    return p.stem


def _is_recording(path: Path) -> bool:
    if _is_bag_folder(path):
        return True
    name = path.name.lower()
    return path.is_file() and any(name.endswith(e) for e in _extensions())


def find_recordings(spec: str | Path, *, exclude: Path | None = None) -> list[Path]:
    """The recordings of a folder (searched recursively) or a glob pattern, sorted.

    A recording is a file with an extension of the io registry (`scanguard.io.READERS`) or a
    ROS 2 bag folder (a folder with ``metadata.yaml``; not searched inside). A folder search
    skips hidden files and folders (names starting with a dot), as a glob pattern does.

    Args:
        spec: A folder, a glob pattern (``**`` recurses), or one recording.
        exclude: A folder not to search (the output folder).

    Raises:
        InputError: Nothing matches, two recordings have the same stem, or a stem cannot
            name a result folder (`scanguard.apps.batch.check_result_names`).
    """
    text = str(spec)
    skip = exclude.resolve() if exclude is not None else None
    found: list[Path] = []
    if any(c in text for c in _GLOB_CHARS):
        found = [Path(p) for p in glob.glob(text, recursive=True) if _is_recording(Path(p))]
    elif Path(text).is_dir() and not _is_bag_folder(Path(text)):
        for root, dirs, files in os.walk(text):
            r = Path(root)
            keep = []
            for d in sorted(dirs):
                sub = r / d
                if d.startswith(".") or (skip is not None and sub.resolve() == skip):
                    continue
                if _is_bag_folder(sub):
                    found.append(sub)
                else:
                    keep.append(d)
            dirs[:] = keep
            # hidden entries are skipped, as a glob pattern skips them
            found += [r / f for f in files if not f.startswith(".") and _is_recording(r / f)]
    elif Path(text).exists():
        found = [Path(text)]
    else:
        raise InputError(text, "no such file or folder (and not a glob pattern)")
    found = sorted(set(found))
    if not found:
        known = ", ".join(sorted(_extensions()))
        raise InputError(text, f"no recordings found (known extensions: {known}, bag folders)")
    check_result_names(found, recording_stem)
    return found


@dataclass(frozen=True)
class RunTask:
    """One recording of `run_many` (picklable: sent to a worker).

    Attributes:
        recording: The recording.
        out_dir: Its result folder (``OUT/<stem>``).
        config: The run settings (``relations`` found next to the recording when unset).
        model: Model file (None: the shipped model).
        runtime: CNN runtime (``onnx`` or ``torch``).
        baseline: Baseline spec (see `scanguard.apps.run_baseline.resolve_baseline`).
        baseline_data: Pair store to fit the baseline on.
        lenient: Skip malformed lines/messages of the recording.
        record: Marker entries of the result folder (``name`` is ``scanguard run``).
    """

    recording: Path
    out_dir: Path
    config: Any
    model: str | None = None
    runtime: str = "onnx"
    baseline: str = "auto"
    baseline_data: str | None = None
    lenient: bool = False
    record: dict[str, Any] = field(default_factory=dict)


def run_task(task: RunTask) -> dict[str, Any]:
    """Run the guarded SLAM of one recording into its result folder (as ``scanguard run``).

    Returns:
        The recording's ``metrics.json`` contents.
    """
    from scanguard.apps.run import run_recording
    from scanguard.apps.run_baseline import resolve_baseline
    from scanguard.apps.run_relations import find_relations
    from scanguard.detect.detector import FaultDetector
    from scanguard.fsutil import ResultDir
    from scanguard.io import read_sequence

    cfg = task.config.model_copy(deep=True)
    if cfg.relations is None:
        found = find_relations(task.recording)
        if found is not None:
            cfg.relations = str(found)
    record = {"name": "scanguard run", "recording": str(task.recording), **task.record}
    result = ResultDir(task.out_dir, record=record)
    seq = read_sequence(task.recording, lenient=task.lenient, max_scans=cfg.max_scans)
    detector = FaultDetector.load(task.model, backend=task.runtime, matcher=cfg.matcher)  # type: ignore[arg-type]
    judge, judge_info = resolve_baseline(task.baseline, task.baseline_data, cfg.matcher)
    with result as tmp:
        run_recording(seq, detector, tmp, config=cfg, baseline=judge, baseline_info=judge_info)
    return _read_metrics(task.out_dir)


def _read_metrics(folder: Path) -> dict[str, Any]:
    data: dict[str, Any] = read_json(folder / "metrics.json", "metrics", None, dict)
    return data


@dataclass
class RecordingResult:
    """One row of the merged table.

    Attributes:
        recording: The recording.
        out_dir: Its result folder.
        status: ``ok``, ``resumed`` (a complete result was already there) or ``failed``.
        metrics: Its ``metrics.json`` (empty when it failed).
        error: The one-line error of a failed recording.
    """

    recording: Path
    out_dir: Path
    status: str
    metrics: dict[str, Any] = field(default_factory=dict)
    error: str | None = None


def run_many(
    recordings: Sequence[Path],
    out: str | Path,
    config: Any,
    executor: Executor,
    *,
    model: str | None = None,
    runtime: str = "onnx",
    baseline: str = "auto",
    baseline_data: str | None = None,
    lenient: bool = False,
    record: dict[str, Any] | None = None,
    on_result: Callable[[RecordingResult], None] | None = None,
    overwrite: bool = False,
) -> list[RecordingResult]:
    """Run every recording (one task each) into ``out/<stem>/``; write the merged table.

    A recording whose folder already holds a complete result (`fsutil.is_complete_result`)
    is not run again (status ``resumed``); a failing one is reported with its error and the
    others go on. The table (`write_results`) is written at the end, atomically.

    Args:
        recordings: The recordings (stems must differ).
        out: Output folder.
        config: The `scanguard.slam.config.RunConfig` of every run.
        executor: Where the tasks run.
        model: Model file (None: the shipped model).
        runtime: CNN runtime.
        baseline: Baseline spec.
        baseline_data: Pair store of the baseline.
        lenient: Skip malformed lines/messages.
        record: Extra marker entries of each result folder (the command line).
        on_result: Called with each result as it arrives (resumed ones first).
        overwrite: Write into a folder that ``run-many`` did not create
            (`scanguard.fsutil.BatchDir`).

    Returns:
        The results, in the order of ``recordings``.

    Raises:
        InputError: A recording's stem cannot name its result folder, or two are the same.
        OutputError: ``out`` is a folder ``run-many`` did not write (without ``overwrite``).
    """
    from scanguard.fsutil import BatchDir

    batch = BatchDir(
        out, overwrite=overwrite, record={**(record or {}), "name": "scanguard run-many"}
    )
    check_result_names(recordings, recording_stem)
    out_path = batch.claim()
    results: dict[Path, RecordingResult] = {}

    def make_task(rec: Path, folder: Path) -> RunTask:
        return RunTask(
            recording=rec,
            out_dir=folder,
            config=config,
            model=model,
            runtime=runtime,
            baseline=baseline,
            baseline_data=baseline_data,
            lenient=lenient,
            record=dict(record or {}),
        )

    folders = [out_path / recording_stem(rec) for rec in recordings]
    for rec, folder, status, metrics, error in resumable(
        recordings, folders, _read_metrics, make_task, run_task, executor
    ):
        results[rec] = RecordingResult(rec, folder, status, metrics or {}, error)
        if on_result is not None:
            on_result(results[rec])
    ordered = [results[r] for r in recordings]
    write_results(ordered, out_path)
    batch.finish([*TABLE_FILES, *(f.name for f in folders)])
    return ordered


#: Fixed columns of the merged table, before the per-trajectory ones.
BASE_COLUMNS = (
    "recording",
    "status",
    "scans",
    "odometry",
    "backend",
    "matcher",
    "accepted",
    "rejected",
    "guard_latency_median_ms",
)


#: Per-trajectory metrics: column prefix -> (metrics.json section, key).
TRAJECTORY_METRICS = (
    ("ate_rmse", "errors", "ate_rmse"),
    ("rpe_trans_rmse", "errors", "rpe_trans_rmse"),
    ("rel_trans_mean", "relations", "trans_mean"),
    ("rel_rot_mean_deg", "relations", "rot_mean_deg"),
)


#: Latency stage of the guard in ``metrics.json``.
GUARD_LATENCY = "guard total"


def result_row(res: RecordingResult) -> dict[str, Any]:
    """The table row of one recording: values exactly as in its ``metrics.json``.

    Per-trajectory columns are ``<metric>[<trajectory>]``: ATE and RPE (translation RMSE)
    where a reference exists, the Kümmerle relation error over all relations (translation and
    rotation means) where relations exist.
    """
    m = res.metrics
    counts = m.get("counts") or {}
    latency = (m.get("latency_ms") or {}).get(GUARD_LATENCY) or {}
    row: dict[str, Any] = {
        "recording": str(res.recording),
        "status": res.status,
        "scans": m.get("n_scans"),
        "odometry": m.get("odometry_source"),
        "backend": m.get("backend"),
        "matcher": m.get("matcher"),
        "accepted": counts.get("accepted"),
        "rejected": counts.get("rejected"),
        "guard_latency_median_ms": latency.get("median"),
    }
    sections = {
        "errors": m.get("errors") or {},
        "relations": (m.get("relations") or {}).get("all") or {},
    }
    for prefix, section, key in TRAJECTORY_METRICS:
        for traj, values in sections[section].items():
            row[f"{prefix}[{traj}]"] = (values or {}).get(key)
    row["error"] = res.error or ""
    return row


def _columns(rows: list[dict[str, Any]]) -> list[str]:
    cols = list(BASE_COLUMNS)
    for prefix, _section, _key in TRAJECTORY_METRICS:
        for row in rows:
            cols += [c for c in row if c.startswith(f"{prefix}[") and c not in cols]
    return [*cols, "error"]


def write_results(results: Sequence[RecordingResult], out: str | Path) -> tuple[Path, Path]:
    """Write ``results.csv`` (full precision) and ``results.md`` into ``out``, atomically.

    Returns:
        The two paths.
    """
    rows = [result_row(r) for r in results]
    note = (
        f"{len(rows)} recordings: "
        + ", ".join(
            f"{sum(r.status == s for r in results)} {s}" for s in ("ok", "resumed", "failed")
        )
        + ". Per-recording results in `<stem>/` (summary.md, metrics.json); "
        "latency in ms, errors in m."
    )
    return write_table(rows, _columns(rows), out, title="scanguard run-many", note=note)
