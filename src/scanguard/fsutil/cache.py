"""Derived artefacts kept between runs in the user's cache folder (never a result).

A cache entry is bytes that scanguard can always make again from its inputs (an ONNX export
of a network, say), stored under ``$XDG_CACHE_HOME/scanguard/<kind>/<key>`` (else
``~/.cache/scanguard/...``), the folder the numba kernels use too. The key names the inputs
(a content hash), so an entry is never stale: different inputs make a different key.

The cache only ever saves time. An entry that cannot be read is made again; one that cannot
be written (a read-only home, a full disk) is logged and skipped, and the run goes on.
Entries are written atomically (`atomic_path`), so two processes filling the same entry at
once each see a whole file.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable
from pathlib import Path

from scanguard.fsutil._paths import atomic_write_bytes

log = logging.getLogger(__name__)

_NAME = re.compile(r"^[A-Za-z0-9._-]{1,128}$")


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/scanguard``, else ``~/.cache/scanguard``."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "scanguard"


def _entry(kind: str, key: str) -> Path:
    for name in (kind, key):
        if not _NAME.match(name) or name in (".", ".."):
            raise ValueError(f"cache entry names must be plain file names, not {name!r}")
    return cache_root() / kind / key


def read_cached(kind: str, key: str) -> bytes | None:
    """The bytes cached under ``kind/key``, or None (missing, empty or unreadable).

    Raises:
        ValueError: ``kind`` or ``key`` is not a plain file name.
    """
    try:
        data = _entry(kind, key).read_bytes()
    except OSError:
        return None  # missing (the usual case) or unreadable
    return data or None


def store_cached(kind: str, key: str, data: bytes) -> None:
    """Store ``data`` under ``kind/key`` (atomically; a cache that cannot be written is skipped).

    Raises:
        ValueError: ``kind`` or ``key`` is not a plain file name.
    """
    path = _entry(kind, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, data)
    except OSError as exc:
        log.debug("not caching %s: %s", path, exc)


def cached_bytes(kind: str, key: str, make: Callable[[], bytes], *, refresh: bool = False) -> bytes:
    """The bytes cached under ``kind/key``, made by ``make`` (and stored) when missing.

    Args:
        kind: Sub-folder of the cache (one per kind of artefact).
        key: File name of the entry: a digest of everything ``make`` depends on.
        make: Makes the bytes; called when the entry is missing or unreadable.
        refresh: Make the bytes and replace the entry even when it exists (the caller found
            the cached bytes unusable: a damaged file).

    Returns:
        The entry's bytes.

    Raises:
        ValueError: ``kind`` or ``key`` is not a plain file name.
    """
    _entry(kind, key)  # names checked before anything is made
    if not refresh:
        data = read_cached(kind, key)
        if data is not None:
            return data
    data = make()
    store_cached(kind, key, data)
    return data
