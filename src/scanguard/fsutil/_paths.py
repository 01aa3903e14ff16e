"""Single files: destination checks, stale temporaries, atomic writes and figures.

Part of the output layer `scanguard.fsutil` (import the public names from there).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

from scanguard.errors import OutputError
from scanguard.fsutil.numba_cache import numba_cache_failure

logger = logging.getLogger(__name__)

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


_DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_DISK_FULL_TEXT = ("no space left on device", "errno = 28", "disk quota exceeded")


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what it wraps) says the disk or the quota is full.

    HDF5 reports a failed write as an `OSError` without ``errno``, with the C library's text
    in its message, so the message is looked at too.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        full = isinstance(e, OSError) and (
            e.errno in _DISK_FULL or any(t in str(e).lower() for t in _DISK_FULL_TEXT)
        )
        if full and not isinstance(e, OutputError):
            return True
        e = e.__cause__ or e.__context__
    return False


def disk_full_error(path: str | Path, exc: BaseException | None = None) -> OutputError:
    """The one-line error of a write to ``path`` that ran out of space.

    Args:
        path: The destination being written.
        exc: The error; when it was raised while numba saved a kernel to its cache (the
            disk of ``NUMBA_CACHE_DIR`` is full, not the output's), the error names the cache
            folder instead.
    """
    cache = None if exc is None else numba_cache_failure(exc)
    if cache is not None:
        return OutputError(
            cache,
            "no space left on device (or quota exceeded) in the numba cache folder "
            "(NUMBA_CACHE_DIR), not in the output: nothing was replaced; free space there or "
            "set NUMBA_CACHE_DIR to a folder with room",
        )
    return OutputError(
        path,
        "no space left on device (or quota exceeded): nothing was replaced; free space "
        "and run again",
    )


_UNSAFE_NAME = re.compile(r"[\x00-\x1f\x7f/\\:]")


def check_file_name(name: str, what: str = "name") -> str:
    """``name`` if it can be one file name inside an output folder, never a path.

    Names from configs and input files (environment names, a shard's ``sequence``) become
    file names; ``../../victim`` or ``/etc/x`` must never lead outside the output folder.

    Raises:
        ValueError: Empty, ``.``/``..``, starting with a dot, longer than 200 characters, or
            holding a separator (slash, backslash, colon) or a control character.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"{what} must be a non-empty string")
    if len(name) > 200:
        raise ValueError(f"{what} is longer than 200 characters")
    if name.startswith(".") or _UNSAFE_NAME.search(name):
        shown = name if len(name) <= 40 else f"{name[:37]}..."
        raise ValueError(
            f"{what} {shown!r} cannot be a file name (no path separators, control characters "
            "or leading dot)"
        )
    return name


def child_path(root: str | Path, rel: str, what: str = "name") -> Path:
    """``root / rel`` checked to stay inside ``root`` once symbolic links are resolved.

    Raises:
        OutputError: ``rel`` is absolute or leads outside ``root`` (names ``root``).
    """
    base = Path(root).resolve()
    target = (base / rel).resolve()
    if Path(rel).is_absolute() or (target != base and base not in target.parents):
        raise OutputError(root, f"{what} {rel!r} leads outside the output folder; refused")
    return Path(root) / rel


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
    refuse_existing: str | None = None,
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
        refuse_existing: For a file: the option that allows replacing an existing one (e.g.
            ``"--overwrite"``); when given, an existing file or a symbolic link (even a
            dangling one) there is refused, the message naming the option. None: an
            existing file is replaced (the command owns the destination).

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
    if refuse_existing is not None and kind == "file" and os.path.lexists(given):
        what = "exists" if st is not None else "is a dangling symbolic link"
        if st is not None and link:
            what = f"exists{link}"
        raise OutputError(
            given, f"{what}: not replaced; choose another name or pass {refuse_existing}"
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
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if is_disk_full(exc):  # one line naming the file; the previous file is untouched
            raise disk_full_error(given, exc) from None
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


def load_figure_writer() -> None:
    """Import what the figures are drawn and written with (matplotlib on Agg), ahead of need.

    ~0.4 s the first time in a process: a run calls it while it waits for its back ends, so
    that its figures at the end do not pay it.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image
    import matplotlib.pyplot


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
