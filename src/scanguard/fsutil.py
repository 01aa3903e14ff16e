"""The output layer: every file and folder scanguard writes goes through this module.

* `check_output_path` checks a destination before any long work: the kind (regular file or
  folder), never a device, FIFO or socket, an extension the command can write, and a parent
  it can write in. Symbolic links are followed: scanguard writes to their target and never
  replaces the link itself.
* `atomic_path` (and `atomic_write_text` / `atomic_write_bytes`) writes one file to a
  temporary sibling and renames it into place, so a crash or Ctrl-C never leaves a
  half-written file and an existing file is only replaced once the new one is complete.
* `ResultDir` writes a whole result folder the same way: into a temporary sibling folder,
  moved into place at the end with a completion marker (`MARKER`: the command line, the
  version, the time and the files written). It refuses to write into a folder that scanguard
  did not create unless ``overwrite`` is given, and then replaces only scanguard's own files.
* Temporaries carry the writer's process id in their name (``.<name>.sg<pid>-<random>...``);
  the ones left behind by a killed process are removed by the next write to the same place
  (`clean_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import secrets
import shutil
import stat
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from scanguard.errors import OutputError

logger = logging.getLogger(__name__)

#: Name of the completion marker of a result folder written by `ResultDir`.
MARKER = ".scanguard-complete.json"

OutputKind = Literal["file", "dir"]

# temporaries: ".<name>.sg<pid>-<8 random chars><rest>" (rest: the suffix, ".partial", ".old")
_TMP_RE = re.compile(r"^\.(?P<name>.*)\.sg(?P<pid>\d+)-[a-z0-9_]{8}(?P<rest>.*)$")
_NAME_MAX = 100  # characters of the destination name kept in a temporary's name
_CLEANED: set[Path] = set()  # folders `atomic_path` has cleaned in this process


def temporary_prefix(name: str) -> str:
    """Name prefix of this process's temporaries next to ``name``.

    Hidden and carrying the pid, so `clean_stale_temporaries` can tell a dead writer's
    leftovers from a live one's.
    """
    return f".{name[:_NAME_MAX]}.sg{os.getpid()}-"


def _what(mode: int) -> str:
    """``'a FIFO'``, ``'a character device'``, ... for an ``st_mode``."""
    for test, name in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "a special file"


def _problem(exc: OSError) -> str:
    """A short, lower-case description of an `OSError` (no path)."""
    text = exc.strerror or str(exc)
    return text[:1].lower() + text[1:]


def resolve_output(path: str | Path) -> Path:
    """The path that writing to ``path`` really writes: symbolic links followed, absolute.

    A dangling link resolves to the file it names (which is then created).
    """
    return Path(os.path.realpath(Path(path).expanduser()))


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def clean_stale_temporaries(folder: str | Path, name: str | None = None) -> list[Path]:
    """Remove the temporaries that a killed scanguard process left in ``folder``.

    A temporary is stale when the process that made it (its id is in the name) is gone.
    A result folder that a killed process had moved aside while swapping in a new one is
    moved back when the new one never arrived.

    Args:
        folder: The folder to clean (nothing happens if it does not exist).
        name: Only the temporaries of this destination name (default: all of them).

    Returns:
        The paths removed (or restored).
    """
    base = Path(folder)
    done: list[Path] = []
    try:
        entries = list(os.scandir(base))
    except OSError:
        return done
    for entry in entries:
        m = _TMP_RE.match(entry.name)
        if m is None or (name is not None and m["name"] != name[:_NAME_MAX]):
            continue
        if _pid_alive(int(m["pid"])):
            continue
        path = Path(entry.path)
        if m["rest"] == ".old":
            dest = base / m["name"]
            if len(m["name"]) < _NAME_MAX and not os.path.lexists(dest):
                with contextlib.suppress(OSError):
                    os.rename(path, dest)
                    logger.warning("%s: restored the previous result (a rerun was killed)", dest)
                    done.append(dest)
                    continue
        _remove(path)
        logger.info("removed %s (left behind by a killed run)", path)
        done.append(path)
    return done


def _suffix_ok(name: str, suffixes: Sequence[str]) -> bool:
    low = name.lower()
    for s in suffixes:
        if s == "" and Path(low).suffix == "":
            return True
        if s and low.endswith(s.lower()):
            return True
    return False


def _expected(suffixes: Sequence[str], kind: OutputKind) -> str:
    parts = [s for s in suffixes if s]
    if "" in suffixes:
        parts.append("no extension (a folder)" if kind == "dir" else "no extension")
    return " or ".join(parts)


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _probe_writable(folder: Path, given: Path) -> None:
    """Create and remove a file in ``folder``; `OutputError` naming ``given`` if that fails."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix("probe"), dir=folder)
    except OSError as exc:
        where = "" if folder == given else f" in {folder}"
        raise OutputError(given, f"cannot write{where}: {_problem(exc)}") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(tmp)


def check_output_path(
    path: str | Path,
    kind: OutputKind = "file",
    *,
    suffixes: Sequence[str] | None = None,
) -> Path:
    """Check an output destination before any long work; return the path to write to.

    The destination may not exist yet (its missing parent folders are created when it is
    written). If it exists it must be of the expected kind: scanguard never replaces a
    device, FIFO or socket, and never a folder by a file or a file by a folder. A symbolic
    link is followed: the returned path is its target.

    Args:
        path: The destination as the user gave it.
        kind: ``"file"`` (a regular file) or ``"dir"`` (a folder).
        suffixes: Accepted extensions, e.g. ``(".onnx",)``; ``""`` accepts a name without
            an extension (``(".mcap", "")`` for a bag file or a bag folder). None: any.

    Returns:
        The resolved (absolute, links followed) destination.

    Raises:
        OutputError: The destination is of the wrong kind or a special file, has an
            unexpected extension, lies under a regular file, or its folder is not writable.
    """
    if not str(path).strip():
        raise OutputError(Path(str(path)), "empty output path")
    given = Path(path).expanduser()
    real = resolve_output(given)
    link = "" if real == given.absolute() else f" (a link to {real})"
    try:
        st = os.stat(real)
    except FileNotFoundError:
        st = None
    except NotADirectoryError:
        st = None  # a parent is not a folder: reported below
    except OSError as exc:
        raise OutputError(given, f"cannot use it{link}: {_problem(exc)}") from None
    if st is not None:
        what = _what(st.st_mode)
        if stat.S_ISDIR(st.st_mode):
            if kind == "file":
                raise OutputError(given, f"is a directory{link}, expected a file")
        elif stat.S_ISREG(st.st_mode):
            if kind == "dir":
                raise OutputError(given, f"is a file{link}, expected a folder")
        else:
            raise OutputError(
                given,
                f"is {what}{link}: scanguard writes only regular files and folders and "
                "never replaces a special file",
            )
    if suffixes is not None and not _suffix_ok(given.name, suffixes):
        raise OutputError(
            given,
            f"unsupported extension {given.suffix!r}: expected {_expected(suffixes, kind)}",
        )
    anchor = _nearest_existing(real.parent)
    if not anchor.is_dir():
        raise OutputError(given, f"{anchor} is not a directory")
    _probe_writable(anchor, given)
    if st is not None and kind == "dir":
        _probe_writable(real, given)
    return real


def _make_parents(folder: Path, given: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return the ones created (outermost first)."""
    missing: list[Path] = []
    p = folder
    while not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(given, f"cannot create {folder}: {_problem(exc)}") from None
    return missing[::-1]


def _check_replaceable(dest: Path, given: Path) -> None:
    """`OutputError` unless ``dest`` is absent or a regular file (after following links)."""
    try:
        st = os.stat(dest)
    except (FileNotFoundError, NotADirectoryError):
        return
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(
            given,
            f"is {_what(st.st_mode)}: scanguard writes only regular files here and never "
            "replaces anything else",
        )


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` on success.

    A symbolic link at ``path`` is followed (its target is written, the link kept). A
    device, FIFO, socket or folder at ``path`` is never replaced. Temporaries of the same
    destination left behind by a killed process are removed first.

    Args:
        path: Final destination.
        suffix: Suffix of the temporary file (defaults to the destination's, so that
            libraries that pick a format from the extension still work).

    Yields:
        The temporary path to write to. It is removed if the block raises.

    Raises:
        OutputError: The destination is not a regular file, or its folder cannot be made.
    """
    given = Path(path)
    dest = resolve_output(given)
    _check_replaceable(dest, given)
    _make_parents(dest.parent, given)
    if dest.parent not in _CLEANED:  # once per folder and process: stale ones do not reappear
        _CLEANED.add(dest.parent)
        clean_stale_temporaries(dest.parent)
    fd, tmp = tempfile.mkstemp(
        prefix=temporary_prefix(dest.name),
        suffix=dest.suffix if suffix is None else suffix,
        dir=dest.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        # mkstemp makes 0600 files: keep the mode of the file replaced, else the umask's
        try:
            mode = stat.S_IMODE(os.stat(dest).st_mode)
        except OSError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp_path, mode)
        yield tmp_path
        _check_replaceable(dest, given)  # it may have changed during the write
        os.replace(tmp_path, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# --- result folders ---------------------------------------------------------------------------


def read_marker(folder: str | Path) -> dict[str, Any] | None:
    """The completion marker of a result folder (None: no marker, or not a readable one)."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
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
            return
        try:
            self._commit()
        except BaseException:
            self._discard()
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


def save_figure(fig: Any, path: str | Path, *, dpi: int = 100) -> Path:
    """Lay out, write (atomically, as PNG) and close a matplotlib figure.

    Args:
        fig: The figure.
        path: The ``.png`` to write.
        dpi: Resolution.

    Returns:
        The written path.
    """
    import matplotlib.pyplot as plt

    out = Path(path)
    try:
        fig.tight_layout()
        with atomic_path(out) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return out
