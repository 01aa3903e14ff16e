"""Safe reading of every input file: the kind of path, then bounded YAML and JSON.

Everything scanguard reads from a user goes through here, so that one hostile file can never
hang a command, exhaust its memory or end in a traceback:

* `check_input_file` (and `check_input_path`, which also takes a bag folder) refuses a FIFO,
  device, socket or folder where a regular file is expected, before anything opens it (opening
  a FIFO blocks until a writer appears).
* `load_yaml` / `loads_yaml` bound the size of the text, its nesting depth and the size of
  the document once its aliases are expanded (the "billion laughs" bomb: 1 KB of nested
  aliases that expands to 10^9 nodes). The check walks libyaml's event stream once, which is
  neither recursive nor expanding, and only a document that passes is constructed.
* `load_json` / `loads_json` bound size and depth the same way.

Every failure is one line naming the file: a `FormatError` (or the ``error`` class asked for,
e.g. `ConfigError` for configs, `ModelError` for model files).
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any

import yaml

from scanguard.errors import FormatError, InputError, ScanGuardError

#: The largest YAML or JSON text read (bytes). Configs, bag metadata and model files written
#: by scanguard are all far below it.
MAX_BYTES = 64 * 1024 * 1024
#: The deepest nesting accepted (mappings and lists). Configs nest to 3 or 4 levels.
MAX_DEPTH = 64
#: The most nodes a YAML document may expand to once its aliases are followed.
MAX_NODES = 1_000_000

_Loader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_input_path(
    path: str | Path,
    *,
    what: str = "file",
    folder: bool = False,
    error: type[ScanGuardError] = InputError,
    missing: str | None = None,
) -> Path:
    """``path`` if it is a regular file (or, with ``folder``, a folder); never opens it.

    Symbolic links are followed. A FIFO, device or socket is refused without being opened,
    so that a command never blocks on it.

    Args:
        path: The input.
        what: What the input is, for the message (``"config file"``, ``"model"``...).
        folder: Whether a folder is accepted too (a ROS 2 bag folder, a dataset).
        error: The error class raised (constructed with one message argument, or with
            ``(path, problem)`` for `InputError` subclasses).
        missing: The problem when the path does not exist (default: "<what> not found").

    Raises:
        ScanGuardError: Missing, or not a regular file / folder (of class ``error``).
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        _raise(error, p, missing or f"{what} not found")
    except OSError as exc:  # a symlink loop, a name too long, no permission on a parent
        _raise(error, p, f"cannot read the {what} ({exc.strerror or exc})")
    if stat.S_ISREG(mode) or (folder and stat.S_ISDIR(mode)):
        return p
    expected = "a regular file or a folder" if folder else "a regular file"
    _raise(error, p, f"{_kind(mode)}, not {expected}: not read as a {what}")
    raise AssertionError  # unreachable; _raise always raises


def check_input_file(
    path: str | Path, *, what: str = "file", error: type[ScanGuardError] = InputError
) -> Path:
    """``path`` if it is a regular file (see `check_input_path`)."""
    return check_input_path(path, what=what, error=error)


def _raise(error: type[ScanGuardError], path: str | Path, problem: str) -> None:
    if issubclass(error, InputError):
        raise error(path, problem)
    raise error(f"{path}: {problem}")


def read_text(
    path: str | Path,
    *,
    what: str = "file",
    error: type[ScanGuardError] = FormatError,
    max_bytes: int = MAX_BYTES,
) -> str:
    """The text of a regular file, bounded in size and decoded as UTF-8 (a BOM is dropped).

    Raises:
        ScanGuardError: Not a regular file, larger than ``max_bytes``, unreadable, or not
            UTF-8 text (of class ``error``; a missing file is one of them).
    """
    p = check_input_file(path, what=what, error=error)
    try:
        with p.open("rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        _raise(error, p, f"cannot read the {what} ({exc.strerror or exc})")
    if len(data) > max_bytes:
        _raise(error, p, f"larger than {max_bytes // (1024 * 1024)} MiB: not a {what}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        _raise(error, p, f"not a text file (binary contents): not a {what}")
    raise AssertionError  # unreachable


def _check_events(loader: Any, max_depth: int, max_nodes: int) -> None:
    """Walk the events of one document: bounded depth and expanded size, without recursion.

    The expanded size of a node is 1 plus that of its children, an alias counting the whole
    size of its anchor's node; sizes are counted bottom up on a stack.

    Raises:
        ValueError: Too deep or too large once expanded (the message says which).
    """
    anchors: dict[str, int] = {}
    # one entry per open collection: [anchor, size so far]
    stack: list[list[Any]] = [[None, 0]]
    while loader.check_event():
        ev = loader.get_event()
        if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            if len(stack) > max_depth:
                raise ValueError(f"nested deeper than {max_depth} levels")
            stack.append([ev.anchor, 1])
            continue
        if isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            anchor, size = stack.pop()
        elif isinstance(ev, yaml.ScalarEvent):
            anchor, size = ev.anchor, 1
        elif isinstance(ev, yaml.AliasEvent):
            if ev.anchor not in anchors:
                raise ValueError(f"alias *{ev.anchor} before its anchor")
            anchor, size = None, anchors[ev.anchor]
        else:  # stream and document start / end
            continue
        if anchor is not None:
            anchors[anchor] = size
        stack[-1][1] += size
        if stack[-1][1] > max_nodes:
            raise ValueError(
                f"expands to more than {max_nodes} values (aliases nested too deep: an alias bomb?)"
            )


def parse_yaml(text: str, *, max_depth: int = MAX_DEPTH, max_nodes: int = MAX_NODES) -> Any:
    """Parse one YAML document with bounded depth and expanded size (safe tags only).

    Args:
        text: The YAML text.
        max_depth: Deepest nesting accepted.
        max_nodes: Most values the document may expand to, aliases followed.

    Raises:
        ValueError: Not YAML, several documents, too deep or too large; the message is the
            problem alone (one line), for the caller to name its source.
    """
    try:
        checker = _Loader(text)
        try:
            _check_events(checker, max_depth, max_nodes)
        finally:
            checker.dispose()
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        raise ValueError(_yaml_problem(exc)) from None
    except RecursionError:
        raise ValueError(f"nested deeper than {max_depth} levels") from None


def loads_yaml(
    text: str,
    source: str,
    *,
    error: type[ScanGuardError] = FormatError,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """`parse_yaml` with its failure as one line naming ``source``.

    Raises:
        ScanGuardError: Not YAML, several documents, too deep or too large (of class
            ``error``).
    """
    try:
        return parse_yaml(text, max_depth=max_depth, max_nodes=max_nodes)
    except ValueError as exc:
        _raise(error, source, f"not valid YAML ({exc})")
    raise AssertionError  # unreachable


def _yaml_problem(exc: yaml.YAMLError) -> str:
    problem = getattr(exc, "problem", None) or " ".join(str(exc).split())
    mark = getattr(exc, "problem_mark", None)
    if mark is not None:
        problem = f"{problem}, line {mark.line + 1} column {mark.column + 1}"
    return str(problem)[:200]


def load_yaml(
    path: str | Path,
    *,
    what: str = "YAML file",
    error: type[ScanGuardError] = FormatError,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """The YAML document of a regular file, read by `read_text` and `loads_yaml`.

    Raises:
        ScanGuardError: See `read_text` and `loads_yaml` (of class ``error``).
    """
    text = read_text(path, what=what, error=error)
    return loads_yaml(text, str(path), error=error, max_depth=max_depth, max_nodes=max_nodes)


def _depth_exceeds(value: Any, max_depth: int) -> bool:
    """Whether a decoded JSON value nests deeper than ``max_depth`` (iteratively)."""
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, (dict, list)):
            if d >= max_depth:
                return True
            children = v.values() if isinstance(v, dict) else v
            stack.extend((c, d + 1) for c in children)
    return False


def loads_json(
    text: str | bytes,
    source: str,
    *,
    error: type[ScanGuardError] = FormatError,
    max_depth: int = MAX_DEPTH,
) -> Any:
    """Parse JSON with bounded depth.

    Raises:
        ScanGuardError: Not JSON or too deep (of class ``error``, naming ``source``).
    """
    try:
        value = json.loads(text)
    except RecursionError:
        problem = f"nested deeper than {max_depth} levels"
    except (ValueError, TypeError) as exc:  # JSONDecodeError and UnicodeDecodeError too
        problem = " ".join(str(exc).split())[:200]
    else:
        if not _depth_exceeds(value, max_depth):
            return value
        problem = f"nested deeper than {max_depth} levels"
    _raise(error, source, f"not valid JSON ({problem})")
    raise AssertionError  # unreachable


def load_json(
    path: str | Path,
    *,
    what: str = "JSON file",
    error: type[ScanGuardError] = FormatError,
    max_depth: int = MAX_DEPTH,
) -> Any:
    """The JSON value of a regular file, read by `read_text` and `loads_json`.

    Raises:
        ScanGuardError: See `read_text` and `loads_json` (of class ``error``).
    """
    text = read_text(path, what=what, error=error)
    return loads_json(text, str(path), error=error, max_depth=max_depth)
