"""`scanguard.fsutil.cache`: derived bytes kept between runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from scanguard.fsutil.cache import cache_root, cached_bytes


def test_made_once_then_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    made: list[bytes] = []

    def make() -> bytes:
        made.append(b"x")
        return b"payload"

    assert cached_bytes("kind", "k1.bin", make) == b"payload"
    assert cached_bytes("kind", "k1.bin", make) == b"payload"
    assert len(made) == 1
    assert (cache_root() / "kind" / "k1.bin").read_bytes() == b"payload"
    assert cached_bytes("kind", "k1.bin", lambda: b"new", refresh=True) == b"new"
    assert (tmp_path / "scanguard" / "kind" / "k1.bin").read_bytes() == b"new"


@pytest.mark.parametrize("name", ["..", "a/b", "", "x" * 200, "a b"])
def test_names_are_plain(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    with pytest.raises(ValueError, match="plain file names"):
        cached_bytes("kind", name, lambda: b"")
    assert not any(tmp_path.iterdir())
