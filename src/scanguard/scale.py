"""Past one process: run independent tasks on a local process pool or on a Ray cluster.

An `Executor` maps a top-level (picklable) function over items and yields ``(item, Outcome)``
in input order; a failing item is reported with its one-line error and the others go on.
`LocalExecutor` uses a ``concurrent.futures.ProcessPoolExecutor`` (spawn start method; one
worker runs in-process), `RayExecutor` Ray tasks (the optional extra
``pip install 'scanguard[scale]'``; ``ray`` is imported only when it is used).

`run_many` runs the guarded SLAM (`scanguard.apps.run.run_recording`, as ``scanguard run``) over
many recordings, one task each, into ``OUT/<recording-stem>/``, resumes finished ones, and writes
one merged results table (``OUT/results.csv`` and ``OUT/results.md``).

`evaluate_many` evaluates a detector on many pair stores (`scanguard.detect.evaluate.
evaluate_store`, as ``scanguard evaluate``), one task each, into ``OUT/<store-name>/``, with the
same resume, failure reporting and merged table.
"""

from __future__ import annotations

import csv
import glob
import io
import json
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from scanguard.errors import ConfigError, InputError, ScanGuardError

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

#: One-line error of ``--executor ray`` without Ray installed.
RAY_MISSING = "--executor ray needs the optional extra: pip install 'scanguard[scale]'"
#: Executor names of ``--executor``.
EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """What one task gave: its value, or the one-line error it failed with.

    Attributes:
        value: The function's return value (None when it failed).
        error: One-line error message (None when it succeeded).
    """

    value: R | None = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Whether the task succeeded."""
        return self.error is None


def error_line(exc: BaseException) -> str:
    """A one-line description of ``exc`` (the message of a `ScanGuardError` as it is)."""
    text = str(exc) if isinstance(exc, ScanGuardError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split()) or type(exc).__name__


def _call(fn: Callable[[T], R], item: T) -> Outcome[R]:
    """Run ``fn(item)``; an exception becomes a failed `Outcome` (top-level: spawn-safe)."""
    try:
        return Outcome(value=fn(item))
    except Exception as exc:
        logger.debug("task %r failed", item, exc_info=True)
        return Outcome(error=error_line(exc))


class Executor(Protocol):
    """Runs a function over items; results in input order, failures isolated."""

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[T, Outcome[R]]]:
        """Yield ``(item, outcome)`` for every item, in input order.

        Args:
            fn: A top-level (picklable) function of one item.
            items: The work items (picklable).
        """
        ...


class LocalExecutor:
    """A local process pool (``workers == 1``: in this process, one item after the other).

    A worker process that dies (killed, out of memory, a crash in native code) breaks the
    pool, and every item still in it with it. Those items are run again, each in a fresh
    process of its own (``workers`` at a time), so a killed worker costs only its own item:
    an item whose own process dies ``retries`` times more is reported as failed.

    Args:
        workers: Worker processes (>= 1).
        retries: Runs in a process of its own for an item hit by a dead worker (>= 0).
    """

    def __init__(self, workers: int = 1, retries: int = 1) -> None:
        if workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        if retries < 0:
            raise ConfigError(f"retries must be >= 0, got {retries}")
        self.workers = workers
        self.retries = retries

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[T, Outcome[R]]]:
        """See `Executor.map`."""
        todo = list(items)
        if self.workers == 1 or len(todo) <= 1:
            for item in todo:
                yield item, _call(fn, item)
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ctx = multiprocessing.get_context("spawn")
        done: dict[int, Outcome[R]] = {}
        hit: list[int] = []  # items of a pool that broke
        shown = 0
        with ProcessPoolExecutor(max_workers=min(self.workers, len(todo)), mp_context=ctx) as pool:
            futures = [pool.submit(_call, fn, item) for item in todo]
            for k, fut in enumerate(futures):
                try:
                    done[k] = fut.result()
                except BrokenProcessPool:
                    hit.append(k)
                except Exception as exc:  # unpicklable item or result
                    done[k] = Outcome(error=f"worker failed: {error_line(exc)}")
                while shown in done:
                    yield todo[shown], done.pop(shown)
                    shown += 1
        if hit:
            logger.warning(
                "a worker process died; %d task(s) run again, each in a process of its own",
                len(hit),
            )
        for start in range(0, len(hit), self.workers):
            chunk = hit[start : start + self.workers]
            for k, outcome in zip(chunk, self._isolated(fn, [todo[k] for k in chunk]), strict=True):
                done[k] = outcome
            while shown in done:
                yield todo[shown], done.pop(shown)
                shown += 1

    def _isolated(self, fn: Callable[[T], R], items: list[T]) -> list[Outcome[R]]:
        """Run each item in a single-process pool of its own (concurrently), with retries."""
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ctx = multiprocessing.get_context("spawn")
        outcomes: list[Outcome[R] | None] = [None] * len(items)
        left = list(range(len(items)))
        for attempt in range(self.retries):
            pools = [ProcessPoolExecutor(max_workers=1, mp_context=ctx) for _ in left]
            try:
                futures = [p.submit(_call, fn, items[k]) for p, k in zip(pools, left, strict=True)]
                again = []
                for k, fut in zip(left, futures, strict=True):
                    try:
                        outcomes[k] = fut.result()
                    except BrokenProcessPool as exc:
                        again.append(k)
                        outcomes[k] = Outcome(error=f"worker failed: {error_line(exc)}")
                    except Exception as exc:
                        outcomes[k] = Outcome(error=f"worker failed: {error_line(exc)}")
                left = again
            finally:
                for p in pools:
                    p.shutdown()
            if not left:
                break
            logger.info("attempt %d: %d task(s) lost their worker again", attempt + 2, len(left))
        return [
            o if o is not None else Outcome(error="worker failed: its process died")
            for o in outcomes
        ]


class RayExecutor:
    """Ray tasks, on a local Ray instance or on an existing cluster.

    Args:
        address: Address of a running cluster (``ray start --head``), or None for a local
            instance started here.
        workers: CPUs of a local instance (None: all); ignored with ``address``.

    Raises:
        ConfigError: Ray is not installed.
    """

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise ConfigError(RAY_MISSING) from None
        self._ray = ray
        self.address = address
        self.workers = workers

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[T, Outcome[R]]]:
        """See `Executor.map`."""
        ray = self._ray
        todo = list(items)
        if not ray.is_initialized():
            if self.address is not None:
                ray.init(address=self.address)
            else:
                ray.init(num_cpus=self.workers)
        task = ray.remote(num_cpus=1)(_call)
        refs = [task.remote(fn, item) for item in todo]
        for item, ref in zip(todo, refs, strict=True):
            try:
                outcome: Outcome[R] = ray.get(ref)
            except Exception as exc:  # a lost worker or node (RayError)
                outcome = Outcome(error=f"worker failed: {error_line(exc)}")
            yield item, outcome


def make_executor(name: str, *, address: str | None = None, workers: int | None = None) -> Any:
    """The executor of ``--executor name`` (checked before any work).

    Raises:
        ConfigError: Unknown name, ``--address`` without Ray, or Ray not installed.
    """
    if name == "local":
        if address is not None:
            raise ConfigError("--address is only used with --executor ray")
        return LocalExecutor(1 if workers is None else workers)
    if name == "ray":
        if workers is not None and workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        return RayExecutor(address=address, workers=workers)
    raise ConfigError(f"--executor must be one of {', '.join(EXECUTORS)}, not {name!r}")


# --- run-many ---------------------------------------------------------------------------------

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
    ROS 2 bag folder (a folder with ``metadata.yaml``; not searched inside).

    Args:
        spec: A folder, a glob pattern (``**`` recurses), or one recording.
        exclude: A folder not to search (the output folder).

    Raises:
        InputError: Nothing matches, or two recordings have the same stem.
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
                if skip is not None and sub.resolve() == skip:
                    continue
                if _is_bag_folder(sub):
                    found.append(sub)
                else:
                    keep.append(d)
            dirs[:] = keep
            found += [r / f for f in files if _is_recording(r / f)]
    elif Path(text).exists():
        found = [Path(text)]
    else:
        raise InputError(text, "no such file or folder (and not a glob pattern)")
    found = sorted(set(found))
    if not found:
        known = ", ".join(sorted(_extensions()))
        raise InputError(text, f"no recordings found (known extensions: {known}, bag folders)")
    check_unique_names(found, recording_stem)
    return found


def check_unique_names(paths: Iterable[Path], name_of: Callable[[Path], str]) -> None:
    """Refuse two inputs whose result folders (``OUT/<name>``) would be the same.

    Raises:
        InputError: Two paths have the same name.
    """
    seen: dict[str, Path] = {}
    for p in paths:
        name = name_of(p)
        if name in seen:
            raise InputError(p, f"same name {name!r} as {seen[name]}: results would collide")
        seen[name] = p


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
    from scanguard.apps.run import find_relations, run_recording
    from scanguard.apps.run_baseline import resolve_baseline
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
    seq = read_sequence(task.recording, lenient=task.lenient)
    detector = FaultDetector.load(task.model, backend=task.runtime, matcher=cfg.matcher)  # type: ignore[arg-type]
    judge, judge_info = resolve_baseline(task.baseline, task.baseline_data, cfg.matcher)
    with result as tmp:
        run_recording(seq, detector, tmp, config=cfg, baseline=judge, baseline_info=judge_info)
    return _read_metrics(task.out_dir)


def _read_json(path: Path, what: str, key: str | None, kind: type) -> Any:
    """``path``'s JSON (its ``key`` entry), checked to be a ``kind``."""
    try:
        data = json.loads(path.read_text())
        if key is not None:
            data = data[key]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"cannot read the {what}: {exc}") from None
    if not isinstance(data, kind):
        raise InputError(path, f"the {what} are not a JSON {kind.__name__}")
    return data


def _read_metrics(folder: Path) -> dict[str, Any]:
    data: dict[str, Any] = _read_json(folder / "metrics.json", "metrics", None, dict)
    return data


def _resumable(
    items: Sequence[Path],
    folders: Sequence[Path],
    read: Callable[[Path], R],
    make_task: Callable[[Path, Path], T],
    fn: Callable[[T], R],
    executor: Executor,
) -> Iterator[tuple[Path, Path, str, R | None, str | None]]:
    """One task per item into its folder, or its complete result read back (resume).

    Yields:
        ``(item, folder, status, value, error)``: the resumed items first (``resumed``), then
        the tasks' outcomes in input order (``ok`` or ``failed`` with the one-line error).
    """
    from scanguard.fsutil import is_complete_result

    todo: list[tuple[Path, Path]] = []
    tasks: list[T] = []
    for item, folder in zip(items, folders, strict=True):
        if is_complete_result(folder):
            try:
                value = read(folder)
            except InputError:
                logger.warning(
                    "%s: complete marker but unreadable result: running it again", folder
                )
            else:
                logger.info("%s: complete result in %s, not run again", item, folder)
                yield item, folder, "resumed", value, None
                continue
        todo.append((item, folder))
        tasks.append(make_task(item, folder))
    for (item, folder), (_task, outcome) in zip(todo, executor.map(fn, tasks), strict=True):
        if outcome.ok and outcome.value is not None:
            yield item, folder, "ok", outcome.value, None
        else:
            logger.info("%s: failed: %s", item, outcome.error)
            yield item, folder, "failed", None, outcome.error


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

    Returns:
        The results, in the order of ``recordings``.
    """
    from scanguard.fsutil import check_output_path

    out_path = check_output_path(out, kind="dir")
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
    for rec, folder, status, metrics, error in _resumable(
        recordings, folders, _read_metrics, make_task, run_task, executor
    ):
        results[rec] = RecordingResult(rec, folder, status, metrics or {}, error)
        if on_result is not None:
            on_result(results[rec])
    ordered = [results[r] for r in recordings]
    write_results(ordered, out_path)
    return ordered


# --- the merged table -------------------------------------------------------------------------

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


def _csv_value(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)  # round-trips exactly
    return str(v)


def _md_value(v: Any) -> str:
    if v is None or v == "":
        return "-"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return str(v).replace("|", "\\|")


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


def write_table(
    rows: Sequence[dict[str, Any]],
    columns: Sequence[str],
    out: str | Path,
    *,
    title: str,
    note: str,
) -> tuple[Path, Path]:
    """Write ``results.csv`` (full precision) and ``results.md`` into ``out``, atomically.

    Args:
        rows: One dict per row (missing columns are empty).
        columns: The columns, in order.
        out: The folder.
        title: Heading of ``results.md``.
        note: Paragraph under the heading.

    Returns:
        The two paths.
    """
    from scanguard.fsutil import atomic_write_text

    cols = list(columns)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    for row in rows:
        writer.writerow([_csv_value(row.get(c)) for c in cols])
    lines = [f"# {title}", "", note, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_md_value(row.get(c)) for c in cols) + " |" for row in rows]
    out_path = Path(out)
    csv_path, md_path = out_path / "results.csv", out_path / "results.md"
    atomic_write_text(csv_path, buf.getvalue())
    atomic_write_text(md_path, "\n".join(lines) + "\n")
    return csv_path, md_path


# --- evaluate over many stores ----------------------------------------------------------------


def store_name(path: str | Path) -> str:
    """The result folder name of a pair store (a build folder's name, a file's stem)."""
    p = Path(path)
    return p.name if p.is_dir() or p.suffix.lower() not in (".h5", ".hdf5") else p.stem


@dataclass(frozen=True)
class EvaluateTask:
    """One store of `evaluate_many` (picklable: sent to a worker).

    Attributes:
        store: The pair store (build folder or ``.h5`` file).
        out_dir: Its result folder (``OUT/<name>``).
        options: Keyword arguments of `scanguard.detect.evaluate.evaluate_store` (``model``
            is a path or None, never a loaded detector).
        record: Marker entries of the result folder (``name`` is ``scanguard evaluate``).
    """

    store: Path
    out_dir: Path
    options: dict[str, Any] = field(default_factory=dict)
    record: dict[str, Any] = field(default_factory=dict)


def evaluate_task(task: EvaluateTask) -> list[dict[str, Any]]:
    """Evaluate one store into its result folder (as ``scanguard evaluate -o``).

    Returns:
        The rows of its ``results.json``.
    """
    from scanguard.detect.evaluate import evaluate_store
    from scanguard.fsutil import ResultDir

    record = {"name": "scanguard evaluate", "store": str(task.store), **task.record}
    result = ResultDir(task.out_dir, record=record)
    opts = dict(task.options)
    model = opts.pop("model", None)
    with result as tmp:
        evaluate_store(model, task.store, tmp, **opts)
    return _read_rows(task.out_dir)


def _read_rows(folder: Path) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = _read_json(
        folder / "results.json", "evaluation rows", "rows", list
    )
    return rows


@dataclass
class StoreResult:
    """One store of `evaluate_many`.

    Attributes:
        store: The pair store.
        out_dir: Its result folder.
        status: ``ok``, ``resumed`` or ``failed``.
        rows: Its result rows (`scanguard.detect.evaluate.COLUMNS`; NaN as None).
        error: The one-line error of a failed store.
    """

    store: Path
    out_dir: Path
    status: str
    rows: list[dict[str, Any]] = field(default_factory=list)
    error: str | None = None


def evaluate_many(
    stores: Sequence[str | Path],
    out: str | Path,
    executor: Executor,
    *,
    record: dict[str, Any] | None = None,
    on_result: Callable[[StoreResult], None] | None = None,
    **options: Any,
) -> list[StoreResult]:
    """Evaluate every store on its own (one task each) into ``out/<name>/``; merged table.

    A store whose folder holds a complete result is not evaluated again (``resumed``); one
    that fails (unreadable, corrupt, nothing to evaluate) is reported with its error and the
    others go on. ``out/results.csv`` and ``out/results.md`` list every row of every store
    with a ``store`` and a ``status`` column, values as in each store's ``results.json``.

    Args:
        stores: Build folders or ``.h5`` files (names must differ, see `store_name`).
        out: Output folder.
        executor: Where the tasks run.
        record: Extra marker entries of each result folder (the command line).
        on_result: Called with each result as it arrives (resumed ones first).
        **options: Keyword arguments of `scanguard.detect.evaluate.evaluate_store`
            (``model`` a path or None, ``splits``, ``baselines``, ``backend``, ...).

    Returns:
        The results, in the order of ``stores``.

    Raises:
        InputError: Two stores have the same name.
    """
    from scanguard.detect.evaluate import COLUMNS
    from scanguard.fsutil import check_output_path

    out_path = check_output_path(out, kind="dir")
    paths = [Path(s) for s in stores]
    check_unique_names(paths, store_name)
    results: dict[Path, StoreResult] = {}

    def make_task(store: Path, folder: Path) -> EvaluateTask:
        return EvaluateTask(store, folder, dict(options), dict(record or {}))

    folders = [out_path / store_name(p) for p in paths]
    for p, folder, status, got, error in _resumable(
        paths, folders, _read_rows, make_task, evaluate_task, executor
    ):
        results[p] = StoreResult(p, folder, status, got or [], error)
        if on_result is not None:
            on_result(results[p])
    ordered = [results[p] for p in paths]
    rows: list[dict[str, Any]] = []
    for r in ordered:
        base = {"store": str(r.store), "status": r.status, "error": r.error or ""}
        rows += [{**base, **row} for row in r.rows] if r.rows else [base]
    n = {st: sum(r.status == st for r in ordered) for st in ("ok", "resumed", "failed")}
    note = (
        f"{len(ordered)} stores: {n['ok']} ok, {n['resumed']} resumed, {n['failed']} failed. "
        "Per-store results in `<name>/` (results.json, roc.png, ...); positive class: fault."
    )
    columns = ["store", "status", *COLUMNS, "error"]
    write_table(rows, columns, out_path, title="scanguard evaluate", note=note)
    return ordered
