"""Result folders written as a whole (`ResultDir`) and their completion markers.

Part of the output layer `scanguard.fsutil` (import the public names from there).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import secrets
import shutil
import tempfile
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from scanguard.errors import OutputError, ScanGuardError
from scanguard.fsutil._paths import (
    _check_replaceable,
    _make_parents,
    _problem,
    atomic_path,
    atomic_write_text,
    check_output_path,
    clean_stale_temporaries,
    disk_full_error,
    is_disk_full,
    resolve_output,
    temporary_prefix,
)
from scanguard.safeload import load_json

logger = logging.getLogger(__name__)

#: Name of the completion marker of a result folder written by `ResultDir`.
MARKER = ".scanguard-complete.json"


def read_marker(folder: str | Path) -> dict[str, Any] | None:
    """The completion marker of a result folder (None: no marker, or not a readable one)."""
    try:
        data = load_json(Path(folder) / MARKER, what="completion marker")
    except ScanGuardError:
        return None
    return data if isinstance(data, dict) else None


def is_complete_result(folder: str | Path) -> bool:
    """Whether ``folder`` holds a complete result written by `ResultDir`."""
    m = read_marker(folder)
    return bool(m and m.get("complete") is True)


def _files_under(folder: Path) -> list[str]:
    """Relative paths (POSIX) of every non-folder entry under ``folder``, sorted."""
    out: list[str] = []
    for root, _dirs, files in os.walk(folder):
        rel_root = Path(root).relative_to(folder)
        out.extend((rel_root / f).as_posix() for f in files)
    return sorted(out)


def _listed(marker: Mapping[str, Any] | None, key: str) -> set[str]:
    """The relative paths a marker lists under ``key``."""
    items = (marker or {}).get(key, [])
    return {str(f) for f in items if isinstance(f, str)} if isinstance(items, list) else set()


def _has_foreign_files(folder: Path, owned: set[str]) -> bool:
    for root, _dirs, files in os.walk(folder):
        rel_root = Path(root).relative_to(folder)
        for f in files:
            rel = (rel_root / f).as_posix()
            if rel != MARKER and rel not in owned:
                return True
    return False


def _json_default(obj: Any) -> Any:
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, tuple)):
        return list(obj)
    item = getattr(obj, "item", None)  # numpy scalars
    if callable(item):
        return item()
    return str(obj)


class ResultDir:
    """Write a result folder as a whole, or not at all.

    Construct it before any long work: the destination is checked then (kind, writable,
    ownership), so a bad ``-o`` fails at once. Entering yields a temporary sibling folder to
    write everything into; on success it is moved into place with a completion marker
    (`MARKER`); on any exception (Ctrl-C included) it is removed, together with the parent
    folders that were created for it, and the destination is left as it was.

    Where the destination already exists:

    * a result of the same command (its marker has the same ``record["name"]``, e.g.
      ``"scanguard run"``) holding only scanguard's files is replaced as a whole (two
      renames);
    * an empty folder, a result of the same command holding other files too, or a result of
      another command (``evaluate -o`` into a ``train`` folder) gets the new files moved in;
      the files of a previous result of the same command that the new one does not have are
      removed, every other file is kept;
    * a non-empty folder without the marker is refused unless ``overwrite`` is given; then the
      new files are moved in (replacing files of the same names) and every other file is kept.

    While files are moved in, the marker says ``"complete": false``, so a kill in that
    moment never passes for a complete result.

    Example:
        >>> result = ResultDir("runs/a", record={"name": "scanguard run"})
        >>> with result as tmp:  # doctest: +SKIP
        ...     (tmp / "summary.md").write_text("...")

    Args:
        path: The result folder.
        overwrite: Allow writing into a non-empty folder that scanguard did not create.
        record: Extra JSON-able entries of the marker: ``name`` (the command, which decides
            whether an earlier result may be replaced as a whole), the command line, ...
        option: How the command names its ``overwrite`` option (for the refusal message).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        overwrite: bool = False,
        record: Mapping[str, Any] | None = None,
        option: str = "--overwrite",
    ) -> None:
        self.given = Path(path)
        self.path = check_output_path(path, kind="dir")
        self.overwrite = overwrite
        self.record = dict(record or {})
        self.option = option
        self.started = datetime.now(UTC)
        self._tmp: Path | None = None
        self._created: list[Path] = []
        clean_stale_temporaries(self.path.parent, self.path.name)
        self._plan()  # refuses a foreign folder now, before any work

    @property
    def tmp(self) -> Path:
        """The temporary folder (only inside the ``with`` block)."""
        if self._tmp is None:
            raise RuntimeError("ResultDir.tmp is only available inside its with block")
        return self._tmp

    def final(self, path: str | Path) -> Path:
        """Where ``path`` (inside the temporary folder) ends up; other paths are returned as is."""
        p = Path(path)
        if self._tmp is not None:
            with contextlib.suppress(ValueError):
                return self.path / p.relative_to(self._tmp)
        return p

    def _plan(self) -> Literal["new", "swap", "merge"]:
        dest = self.path
        if not os.path.lexists(dest):
            return "new"
        if not dest.is_dir():
            raise OutputError(self.given, "exists and is not a folder")
        marker = read_marker(dest)
        if marker is None:
            if not any(os.scandir(dest)):
                return "merge"
            if not self.overwrite:
                raise OutputError(
                    self.given,
                    "folder exists and was not written by scanguard (it has no "
                    f"{MARKER}): choose another output folder, or pass {self.option} to "
                    "write into it (only files of the same names are replaced)",
                )
            return "merge"
        owned = _listed(marker, "files")
        cwd = Path.cwd().resolve()
        if (
            not self._same_command(marker)
            or _listed(marker, "other_files")
            or cwd == dest
            or dest in cwd.parents
            or _has_foreign_files(dest, owned)
        ):
            return "merge"
        return "swap"

    def _same_command(self, marker: Mapping[str, Any] | None) -> bool:
        """Whether ``marker`` is of a result of the same command (then it may be replaced)."""
        name = self.record.get("name")
        return bool(marker) and name is not None and marker.get("name") == name  # type: ignore[union-attr]

    def __enter__(self) -> Path:
        self._created = _make_parents(self.path.parent, self.given)
        try:
            tmp = Path(
                tempfile.mkdtemp(
                    prefix=temporary_prefix(self.path.name), suffix=".partial", dir=self.path.parent
                )
            )
        except OSError as exc:
            self._remove_created()
            raise OutputError(self.given, f"cannot write next to it: {_problem(exc)}") from None
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)
        self._tmp = tmp
        return tmp

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self._discard()
            if exc is not None and is_disk_full(exc):  # one line naming the folder
                raise disk_full_error(self.given, exc) from None
            return
        try:
            self._commit()
        except BaseException as err:
            self._discard()
            if is_disk_full(err):
                raise disk_full_error(self.given, err) from None
            raise

    def _remove_created(self) -> None:
        for p in reversed(self._created):
            with contextlib.suppress(OSError):
                p.rmdir()
        self._created = []

    def _discard(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
        self._remove_created()

    def _marker(
        self, files: list[str], *, complete: bool, other_files: list[str] | None = None
    ) -> str:
        from scanguard import __version__

        data = {
            "complete": complete,
            "scanguard": __version__,
            "started": self.started.isoformat(timespec="seconds"),
            "finished": datetime.now(UTC).isoformat(timespec="seconds"),
            **self.record,
            "files": files,
            "other_files": other_files or [],
        }
        return json.dumps(data, indent=1, default=_json_default) + "\n"

    def _commit(self) -> None:
        tmp = self.tmp
        files = [f for f in _files_under(tmp) if f != MARKER]
        mode = self._plan()  # again: the destination may have changed during the work
        dest = self.path
        if mode == "new":
            (tmp / MARKER).write_text(self._marker(files, complete=True))
            os.rename(tmp, dest)
        elif mode == "swap":
            (tmp / MARKER).write_text(self._marker(files, complete=True))
            old = dest.parent / f"{temporary_prefix(dest.name)}{secrets.token_hex(4)}.old"
            os.rename(dest, old)
            try:
                os.rename(tmp, dest)
            except BaseException:
                os.rename(old, dest)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            self._merge(files)
        self._tmp = None
        self._created = []
        logger.debug("%s: result complete (%d files, %s)", dest, len(files), mode)

    def _merge(self, files: list[str]) -> None:
        tmp, dest = self.tmp, self.path
        old = read_marker(dest)
        old_files = _listed(old, "files")
        # files of earlier results of other commands: scanguard's, never removed here
        others = _listed(old, "other_files") | (set() if self._same_command(old) else old_files)
        if not self._same_command(old):
            old_files = set()
        targets: dict[str, Path] = {}
        for rel in files:  # check every target before touching anything
            target = resolve_output(dest / rel)
            _check_replaceable(target, dest / rel)
            targets[rel] = target
        new = set(files)
        atomic_write_text(
            dest / MARKER,
            self._marker(sorted(old_files | new), complete=False, other_files=sorted(others - new)),
        )
        for rel, target in targets.items():
            _make_parents(target.parent, dest / rel)
            _move_file(tmp / rel, target)
        for rel in sorted(old_files - new):  # the previous result's files it no longer has
            p = dest / rel
            if p.is_file() and not p.is_symlink():
                with contextlib.suppress(OSError):
                    p.unlink()
        others = {rel for rel in others - new if (dest / rel).is_file()}
        atomic_write_text(
            dest / MARKER, self._marker(files, complete=True, other_files=sorted(others))
        )
        shutil.rmtree(tmp, ignore_errors=True)


def _move_file(src: Path, dst: Path) -> None:
    """Rename ``src`` onto ``dst``; copy atomically when they are on different file systems."""
    try:
        os.replace(src, dst)
    except OSError as exc:
        if exc.errno != errno.EXDEV:
            raise
        with atomic_path(dst) as t:
            shutil.copyfile(src, t)


class BatchDir:
    """A result folder filled piece by piece: one sub-result per input, then one table.

    ``run-many`` and ``evaluate --per-store`` write ``OUT/<name>/`` per input (each a
    `ResultDir`, resumable) and ``OUT/results.csv``; the folder cannot be swapped in as a
    whole. It is claimed instead: construct it before any work (a user's folder is refused
    then), `claim` it before the first input (its marker says ``"complete": false`` and
    names the command, so a rerun resumes into it), `finish` it after the table is written.

    A folder is accepted when it is new, empty, or claimed by the same command before; a
    non-empty folder without a marker, or one holding another command's result, only with
    ``overwrite`` (files of the same names are then replaced, every other file is kept).

    Args:
        path: The folder.
        overwrite: Allow a folder that this command did not claim.
        record: Marker entries; ``name`` (the command) decides what a rerun may resume.
        option: How the command names its ``overwrite`` option (for the refusal message).

    Raises:
        OutputError: The folder is refused (see above), or is not a writable folder.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        overwrite: bool = False,
        record: Mapping[str, Any] | None = None,
        option: str = "--overwrite",
    ) -> None:
        self.given = Path(path)
        self.path = check_output_path(path, kind="dir")
        self.record = dict(record or {})
        self.started = datetime.now(UTC)
        marker = read_marker(self.path) if self.path.is_dir() else None
        if overwrite or not self.path.is_dir():
            return
        if marker is None and any(os.scandir(self.path)):
            raise OutputError(
                self.given,
                f"folder exists and was not written by scanguard (it has no {MARKER}): "
                f"choose another output folder, or pass {option} to write into it (only files "
                "of the same names are replaced)",
            )
        if marker is not None and marker.get("name") != self.record.get("name"):
            raise OutputError(
                self.given,
                f"holds a result of {_short_name(marker)}: choose another output folder, or "
                f"pass {option} to write into it (only files of the same names are replaced)",
            )

    def _write_marker(self, files: list[str], *, complete: bool) -> None:
        from scanguard import __version__

        data = {
            "complete": complete,
            "scanguard": __version__,
            "started": self.started.isoformat(timespec="seconds"),
            "finished": datetime.now(UTC).isoformat(timespec="seconds"),
            **self.record,
            "files": files,
            "other_files": [],
        }
        atomic_write_text(self.path / MARKER, json.dumps(data, indent=1, default=_json_default))

    def claim(self) -> Path:
        """Create the folder (if needed) and mark it as this command's, unfinished."""
        _make_parents(self.path, self.given)
        self._write_marker([], complete=False)
        return self.path

    def finish(self, files: list[str]) -> None:
        """Mark the folder complete, listing ``files`` (relative paths) as the command's."""
        self._write_marker(sorted(files), complete=True)


def _short_name(marker: Mapping[str, Any]) -> str:
    name = marker.get("name")
    return f"`{name}`" if isinstance(name, str) and name else "another scanguard command"
