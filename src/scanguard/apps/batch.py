"""What the many-input workflows share: one task per input, resume, one merged table.

`run_many` (`scanguard.apps.run_many`) and `evaluate_many` (`scanguard.apps.evaluate_many`)
give every input its own result folder (``OUT/<name>/``), skip the inputs whose folder
already holds a complete result, report a failing input with its one-line error while the
others go on, and write one merged table (``OUT/results.csv`` and ``OUT/results.md``).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

from scanguard.errors import InputError
from scanguard.runtime.executor import Executor
from scanguard.safeload import load_json

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")


#: The files a batch command writes into its output folder itself (never a result's name).
TABLE_FILES = ("results.csv", "results.md")


def check_result_names(paths: Iterable[Path], name_of: Callable[[Path], str]) -> None:
    """Refuse inputs whose result folders (``OUT/<name>``) would not be their own.

    A name comes from a file name (``..clf`` has the stem ``..``): it must be one plain
    folder name inside ``OUT`` (`scanguard.fsutil.check_file_name`: no separator, no
    leading dot), differ from the table files (`TABLE_FILES`, case ignored) and from every
    other input's name.

    Raises:
        InputError: A name cannot be a folder in ``OUT``, or two inputs have the same name.
    """
    from scanguard.fsutil import check_file_name

    seen: dict[str, Path] = {}
    for p in paths:
        name = name_of(p)
        try:
            check_file_name(name, "result folder name")
        except ValueError as exc:
            raise InputError(p, f"{exc}: rename the input") from None
        if name.lower() in TABLE_FILES:
            raise InputError(
                p, f"result folder name {name!r} is one of the table files: rename the input"
            )
        if name in seen:
            raise InputError(p, f"same name {name!r} as {seen[name]}: results would collide")
        seen[name] = p


def read_json(path: Path, what: str, key: str | None, kind: type) -> Any:
    """``path``'s JSON (its ``key`` entry), checked to be a ``kind``.

    Raises:
        InputError: The file is missing, not JSON, lacks ``key`` or is not a ``kind``.
    """
    data = load_json(path, what=what, error=InputError)
    try:
        if key is not None:
            data = data[key]
    except (KeyError, TypeError, IndexError) as exc:
        raise InputError(path, f"cannot read the {what}: {exc}") from None
    if not isinstance(data, kind):
        raise InputError(path, f"the {what} are not a JSON {kind.__name__}")
    return data


def resumable(
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


def _csv_value(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)  # round-trips exactly
    return str(v)


_MD_BREAKS = re.compile(r"[\x00-\x1f\x7f\u2028\u2029\x85]+")


def md_cell(text: str) -> str:
    """``text`` as one Markdown table cell (a name from a file never breaks the table).

    Line breaks and control characters become one space; ``|`` and backslashes are escaped.
    """
    return _MD_BREAKS.sub(" ", str(text)).replace("\\", "\\\\").replace("|", "\\|")


def _md_value(v: Any) -> str:
    if v is None or v == "":
        return "-"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return md_cell(str(v))


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
    header = "| " + " | ".join(md_cell(c) for c in cols) + " |"
    lines = [f"# {md_cell(title)}", "", note, "", header, "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_md_value(row.get(c)) for c in cols) + " |" for row in rows]
    out_path = Path(out)
    csv_path, md_path = out_path / "results.csv", out_path / "results.md"
    atomic_write_text(csv_path, buf.getvalue())
    atomic_write_text(md_path, "\n".join(lines) + "\n")
    return csv_path, md_path
