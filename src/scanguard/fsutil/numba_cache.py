"""Where numba keeps scanguard's compiled kernels, and a bound on how much it keeps.

By default numba writes its cache next to the source (the installed package's
``__pycache__``), which may be read-only or shared. `configure_numba_cache` (called when
``scanguard`` is imported) points ``NUMBA_CACHE_DIR`` at the user's cache folder,
``$XDG_CACHE_HOME/scanguard/numba`` or ``~/.cache/scanguard/numba``, unless the variable is
already set (then it is left alone, and so is that folder). numba reads the variable when it
is first imported; when it was imported earlier, its configuration is updated too, before any
scanguard kernel is defined.

The cache keys of scanguard's kernels are stable, so a kernel compiled once is reused by
every later process. What still accumulates are entries of older scanguard versions (a
kernel's index is named after its line, so an edit or upgrade leaves the previous files
unused), and the kernels of other installations (numba names a source folder's cache
subfolder after that folder's path, so every checkout or virtual environment has its own).
`prune_numba_cache` bounds the folder: when it holds more than ``max_bytes``, it removes the
kernels of other installations first, then this one's, each the kernels compiled longest
ago first (an index file with its data files); a removed kernel is simply compiled again when
next needed. Other installations go first because a process only ever loads its own: with
ages alone, a machine with many checkouts evicted the running one's kernels at every start,
and each run compiled seconds of them again (`tests/test_numba_cache.py`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import sys
from collections.abc import Collection
from pathlib import Path

log = logging.getLogger(__name__)

MAX_CACHE_BYTES = 256 * 1024 * 1024
"""Default bound of the scanguard numba cache folder (one version's kernels take ~10 MB)."""


def default_numba_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/scanguard/numba``, else ``~/.cache/scanguard/numba``."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "scanguard" / "numba"


def configure_numba_cache() -> Path | None:
    """Set ``NUMBA_CACHE_DIR`` to `default_numba_cache_dir` unless it is set already.

    Returns:
        The folder chosen here, or None when the user's ``NUMBA_CACHE_DIR`` stands.
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    path = default_numba_cache_dir()
    os.environ["NUMBA_CACHE_DIR"] = str(path)
    # numba copies the variable into its config once, on first import; kernels read the
    # config when they are defined, which happens after this in every scanguard module
    config = sys.modules.get("numba.core.config")
    if config is not None and not getattr(config, "CACHE_DIR", ""):
        setattr(config, "CACHE_DIR", str(path))  # noqa: B010 (a module typed without it)
    return path


def cache_subfolder(source_dir: str | Path) -> str:
    """The subfolder of the cache in which numba keeps the kernels of ``source_dir``'s files.

    numba's own rule (``numba.core.caching._CacheLocator.get_suitable_cache_subpath``, private,
    so restated here and checked against it in the tests): the folder's name, ``_``, and the
    SHA-1 of its absolute path.
    """
    path = os.path.abspath(source_dir)
    return f"{os.path.basename(path)}_{hashlib.sha1(path.encode()).hexdigest()}"


def own_cache_subfolders() -> set[str]:
    """The cache subfolders of this installation's package folders (see `cache_subfolder`)."""
    package = Path(__file__).resolve().parent.parent
    folders = [package, *(p for p in package.rglob("*") if p.is_dir() and p.name != "__pycache__")]
    return {cache_subfolder(p) for p in folders}


def prune_numba_cache(
    root: str | Path, max_bytes: int = MAX_CACHE_BYTES, keep: Collection[str] | None = None
) -> int:
    """Remove the least recently compiled kernels until ``root`` holds at most ``max_bytes``.

    A kernel is an index file (``*.nbi``) with its data files (``<index stem>.<n>.nbc``);
    its age is that of its newest file (numba rewrites them when it compiles). Data files
    whose index is gone are removed first, then the kernels outside the subfolders named in
    ``keep`` (other installations'; by default `own_cache_subfolders`), then those in them,
    oldest first. Errors (a file removed by another process, a read-only folder) are
    ignored: the cache is only an optimisation.

    Returns:
        The number of files removed.
    """
    groups: dict[Path, list[tuple[Path, int, float]]] = {}
    try:
        for folder, _dirs, files in os.walk(root):
            for name in files:
                if not name.endswith((".nbi", ".nbc")):
                    continue
                p = Path(folder) / name
                st = p.stat()
                # "<stem>.nbi" and "<stem>.<n>.nbc" share the key "<folder>/<stem>"
                stem = name[:-4] if name.endswith(".nbi") else name[:-4].rsplit(".", 1)[0]
                groups.setdefault(Path(folder) / stem, []).append((p, st.st_size, st.st_mtime))
    except OSError:
        return 0
    total = sum(size for files in groups.values() for _p, size, _t in files)
    if total <= max_bytes:
        return 0
    own = own_cache_subfolders() if keep is None else keep

    def age(key: Path) -> tuple[bool, bool, float]:
        files = groups[key]
        has_index = any(p.suffix == ".nbi" for p, _s, _t in files)
        return (has_index, key.parent.name in own, max(t for _p, _s, t in files))

    removed = 0
    for key in sorted(groups, key=age):
        if total <= max_bytes:
            break
        for p, size, _t in groups[key]:
            try:
                p.unlink()
            except OSError:
                continue
            total -= size
            removed += 1
    log.debug("numba cache %s: removed %d old file(s)", root, removed)
    return removed


def numba_cache_failure(exc: BaseException) -> Path | None:
    """The cache folder when ``exc`` (or what it wraps) was raised in numba's cache code.

    numba saves a compiled kernel while a command runs; a full disk there raises an
    `OSError` without a file name, which the output layer would otherwise report as its own
    destination being full. The frames of the traceback tell: one in
    ``numba/core/caching.py`` names the file it wrote (``filepath``) or its folder.

    Returns:
        The folder (the one numba wrote to if a frame says, else ``NUMBA_CACHE_DIR``), or
        None when the error did not come from numba's cache.
    """
    found: Path | None = None
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        tb = e.__traceback__
        while tb is not None:
            if tb.tb_frame.f_code.co_filename.replace("\\", "/").endswith("numba/core/caching.py"):
                local = tb.tb_frame.f_locals
                if isinstance(local.get("filepath"), str):
                    return Path(local["filepath"]).parent
                folder = getattr(local.get("self"), "_cache_path", None)
                if isinstance(folder, str):
                    found = Path(folder)
                elif found is None:
                    found = Path(os.environ.get("NUMBA_CACHE_DIR") or default_numba_cache_dir())
            tb = tb.tb_next
        e = e.__cause__ or e.__context__
    return found


def setup_numba_cache() -> None:
    """`configure_numba_cache`, then `prune_numba_cache` of the folder chosen (if any)."""
    path = configure_numba_cache()
    if path is not None and path.is_dir():
        prune_numba_cache(path)
