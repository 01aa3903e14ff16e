"""``scanguard evaluate --per-store``: a detector on many pair stores, one merged table.

`evaluate_many` evaluates a detector on many pair stores (`scanguard.detect.evaluate.
evaluate_store`, as ``scanguard evaluate``), one task each, into ``OUT/<store-name>/``, with
the resume and failure reporting of `scanguard.apps.batch` and one merged table.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scanguard.apps.batch import TABLE_FILES, check_result_names, read_json, resumable, write_table
from scanguard.runtime.executor import Executor


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
    rows: list[dict[str, Any]] = read_json(folder / "results.json", "evaluation rows", "rows", list)
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
    overwrite: bool = False,
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
        overwrite: Write into a folder that ``evaluate --per-store`` did not create
            (`scanguard.fsutil.BatchDir`).
        **options: Keyword arguments of `scanguard.detect.evaluate.evaluate_store`
            (``model`` a path or None, ``splits``, ``baselines``, ``backend``, ...).

    Returns:
        The results, in the order of ``stores``.

    Raises:
        InputError: Two stores have the same name, or a name cannot be a result folder.
        OutputError: ``out`` is a folder this command did not write (without ``overwrite``).
    """
    from scanguard.detect.evaluate import COLUMNS
    from scanguard.fsutil import BatchDir

    batch = BatchDir(
        out,
        overwrite=overwrite,
        record={**(record or {}), "name": "scanguard evaluate --per-store"},
    )
    paths = [Path(s) for s in stores]
    check_result_names(paths, store_name)
    out_path = batch.claim()
    results: dict[Path, StoreResult] = {}

    def make_task(store: Path, folder: Path) -> EvaluateTask:
        return EvaluateTask(store, folder, dict(options), dict(record or {}))

    folders = [out_path / store_name(p) for p in paths]
    for p, folder, status, got, error in resumable(
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
    batch.finish([*TABLE_FILES, *(f.name for f in folders)])
    return ordered
