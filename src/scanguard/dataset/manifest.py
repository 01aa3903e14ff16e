"""Safe updates of a build directory: file locks, manifest read-modify-write, temp clean-up.

Several ``dataset build`` processes may write into one directory at the same time (two
``--recording`` builds, or a simulated build next to a recording build). Two locks in the
directory keep them from losing each other's work:

* ``.scanguard-manifest.lock``: held exclusively (``fcntl.flock``) around every
  read-modify-write of ``manifest.json`` (`update_manifest`), so an update never overwrites
  an entry another process has just added;
* ``.scanguard-build.lock``: held shared by every build for its whole duration
  (`build_session`). A build that can briefly take it exclusively knows no other build is
  running, and only then removes the temporary files a killed write left behind
  (`clean_temporary_files`): a running build's own temporary files are never touched.

Where ``fcntl`` is not available (Windows) the locks are no-ops.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from scanguard.dataset.shards import FORMAT, FORMAT_VERSION, SEQUENCE_DIR
from scanguard.dataset.store import MANIFEST, read_manifest, write_manifest
from scanguard.errors import InputError

try:  # POSIX only
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

MANIFEST_LOCK = ".scanguard-manifest.lock"
BUILD_LOCK = ".scanguard-build.lock"
_LOCKS = (MANIFEST_LOCK, BUILD_LOCK)
#: Files of the build directory itself that an interrupted atomic write may leave behind.
_TOP_LEVEL_TEMP_PREFIXES = (f".{MANIFEST}.", ".config.yaml.")


def _open_lock(directory: Path, name: str) -> int:
    path = directory / name
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise InputError(path, f"cannot create the lock file ({exc.strerror or exc})") from None


@contextlib.contextmanager
def manifest_lock(directory: str | Path) -> Iterator[None]:
    """Hold the directory's manifest lock (exclusive, blocking) for the ``with`` block."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    fd = _open_lock(d, MANIFEST_LOCK)
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def update_manifest(
    directory: str | Path, change: Callable[[dict[str, Any]], dict[str, Any]]
) -> dict[str, Any]:
    """Read ``manifest.json``, apply ``change``, write it back, all under the manifest lock.

    Args:
        directory: Build directory.
        change: Gets the current manifest (a fresh ``{"format", "format_version",
            "sequences": []}`` when there is none yet) and returns the new one.

    Returns:
        The manifest written.

    Raises:
        InputError: The existing manifest is unreadable or malformed.
    """
    d = Path(directory)
    with manifest_lock(d):
        current: dict[str, Any] = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "sequences": [],
        }
        if (d / MANIFEST).exists():
            current = read_manifest(d)
        new = change(current)
        write_manifest(d, new)
    return new


def _is_temporary(name: str, top_level: bool) -> bool:
    if name in _LOCKS:
        return False
    if ".tmp" in name:
        return True
    if top_level:
        return name.startswith(_TOP_LEVEL_TEMP_PREFIXES)
    # `scanguard.fsutil.atomic_path` writes ".<name>.<random><suffix>" next to the target
    return name.startswith(".")


def clean_temporary_files(directory: str | Path) -> list[Path]:
    """Remove what killed atomic writes left in a build directory (no other build may run).

    Removed: hidden or ``*.tmp*`` files in ``sequences/`` (partial ``.h5`` files) and the
    temporary copies of ``manifest.json`` / ``config.yaml`` next to them. Finished files and
    the lock files are kept. Call it only while holding the build lock exclusively (see
    `build_session`).

    Returns:
        The paths removed.
    """
    d = Path(directory)
    removed: list[Path] = []
    for folder, top in ((d, True), (d / SEQUENCE_DIR, False)):
        if not folder.is_dir():
            continue
        for path in sorted(folder.iterdir()):
            if not _is_temporary(path.name, top) or not (path.is_file() or path.is_symlink()):
                continue
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                removed.append(path)
    if removed:
        log.info(
            "%s: removed %d temporary file(s) of an interrupted build (%s)",
            d,
            len(removed),
            ", ".join(p.name for p in removed[:3]) + (", ..." if len(removed) > 3 else ""),
        )
    return removed


@contextlib.contextmanager
def build_session(directory: str | Path) -> Iterator[Path]:
    """Hold the build lock (shared) while building into ``directory``; clean up first.

    When no other build holds the lock, temporary files of killed writes are removed before
    the build starts (`clean_temporary_files`); when another build is running they are left
    alone (they may be its own files in progress).

    Yields:
        The directory (created, with its ``sequences/`` folder).
    """
    d = Path(directory)
    try:
        (d / SEQUENCE_DIR).mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(d, "exists and is not a directory") from None
    except NotADirectoryError:
        raise InputError(d, "a parent of the build directory is not a directory") from None
    fd = _open_lock(d, BUILD_LOCK)
    try:
        if fcntl is None:  # pragma: no cover - Windows
            yield d
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            log.info("%s: another build is running here; temporary files are left alone", d)
        else:
            clean_temporary_files(d)
        fcntl.flock(fd, fcntl.LOCK_SH)  # converts an exclusive lock; waits for none
        yield d
    finally:
        os.close(fd)
