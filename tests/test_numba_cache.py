"""numba's cache: reused across processes, in the user's cache folder, bounded in size."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numba
from numba.core.caching import _CacheLocator

import scanguard.matching._core as core
from scanguard.fsutil.numba_cache import cache_subfolder, own_cache_subfolders, prune_numba_cache

MATCH = """
import numpy as np
from scanguard.matching.registry import get_matcher

a = np.linspace(0, 2 * np.pi, 120, endpoint=False)
tgt = np.stack([4 * np.cos(a), 2.5 * np.sin(a)], 1)
c, s = np.cos(0.05), np.sin(0.05)
src = (tgt - [0.1, 0.05]) @ np.array([[c, -s], [s, c]])
print(repr(get_matcher("icp")(src, tgt).pose.tolist()))
"""


def _run(code: str, env: dict[str, str]) -> str:
    res = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout.strip()


def _files(root: Path) -> dict[str, float]:
    return {str(p.relative_to(root)): p.stat().st_mtime for p in root.rglob("*") if p.is_file()}


def test_matching_kernels_are_reused_by_the_next_process(tmp_path: Path) -> None:
    cache = tmp_path / "numba"
    # start from a copy of this process's cache (same source folders, so the same entries),
    # warmed once per machine: no cold compile in the test from then on
    shared = numba.config.CACHE_DIR
    if shared:
        _run(MATCH, {**os.environ, "NUMBA_CACHE_DIR": shared})
        shutil.copytree(shared, cache)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    first = _run(MATCH, env)
    after_first = _files(cache)
    assert any(name.endswith(".nbc") and "run-" in name for name in after_first)
    second = _run(MATCH, env)
    assert second == first  # same pose, bit for bit
    # nothing added, nothing rewritten: the second process loaded what the first left
    assert _files(cache) == after_first


def test_cache_folder_defaults_to_the_user_cache_and_respects_the_variable(
    tmp_path: Path,
) -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    show = (
        "import scanguard, numba, os; print(numba.config.CACHE_DIR, os.environ['NUMBA_CACHE_DIR'])"
    )
    want = str(tmp_path / "xdg" / "scanguard" / "numba")
    assert _run(show, env).split() == [want, want]
    # numba imported before scanguard: its configuration is updated all the same
    assert _run("import numba; " + show, env).split() == [want, want]
    mine = str(tmp_path / "mine")
    assert _run(show, {**env, "NUMBA_CACHE_DIR": mine}).split() == [mine, mine]


def _kernel(folder: Path, stem: str, sizes: list[int], mtime: float, index: bool = True) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{stem}.nbi"] if index else []
    names += [f"{stem}.{i + 1}.nbc" for i in range(len(sizes) - len(names))]
    for name, size in zip(names, sizes, strict=True):
        (folder / name).write_bytes(b"x" * size)
        os.utime(folder / name, (mtime, mtime))


def test_prune_removes_the_oldest_kernels_until_under_the_bound(tmp_path: Path) -> None:
    a, b = tmp_path / "matching_1", tmp_path / "sim_2"
    _kernel(a, "_core.f-10.py311", [100, 1000], mtime=1000)  # oldest kernel
    _kernel(a, "_core.g-20.py311", [100, 1000, 1000], mtime=3000)
    _kernel(b, "raycast.h-5.py311", [100, 1000], mtime=2000)
    _kernel(b, "raycast.gone-7.py311", [500], mtime=5000, index=False)  # orphan data file
    (b / "notes.txt").write_text("not numba's")
    assert prune_numba_cache(tmp_path, max_bytes=10_000) == 0  # under the bound: untouched
    # 4800 bytes in all; a 3500-byte bound removes the orphan, then the oldest kernel
    assert prune_numba_cache(tmp_path, max_bytes=3500) == 3
    left = sorted(p.name for p in tmp_path.rglob("*") if p.is_file())
    assert left == [
        "_core.g-20.py311.1.nbc",
        "_core.g-20.py311.2.nbc",
        "_core.g-20.py311.nbi",
        "notes.txt",
        "raycast.h-5.py311.1.nbc",
        "raycast.h-5.py311.nbi",
    ]
    assert prune_numba_cache(tmp_path, max_bytes=2100) == 2  # then the next oldest
    assert prune_numba_cache(tmp_path / "absent") == 0


def test_subfolder_names_follow_numbas_rule() -> None:
    # the rule is restated from numba's private locator: this is where a numba upgrade that
    # changed it would show
    source = Path(core.__file__)
    assert cache_subfolder(source.parent) == _CacheLocator.get_suitable_cache_subpath(str(source))
    assert cache_subfolder(source.parent) in own_cache_subfolders()


def test_prune_removes_other_installations_kernels_before_this_ones(tmp_path: Path) -> None:
    mine = cache_subfolder(Path(core.__file__).parent)
    _kernel(tmp_path / mine, "_core.f-10.py311", [100, 1000], mtime=1000)  # oldest, but ours
    _kernel(tmp_path / "matching_0ther", "_core.f-10.py311", [100, 1000], mtime=4000)
    _kernel(tmp_path / "matching_0ther", "_core.g-20.py311", [100, 1000], mtime=5000)
    # a machine with many checkouts: the running one's kernels were evicted at every start
    assert prune_numba_cache(tmp_path, max_bytes=2500) == 2
    assert sorted(p.name for p in (tmp_path / mine).iterdir()) == [
        "_core.f-10.py311.1.nbc",
        "_core.f-10.py311.nbi",
    ]
    assert len(list((tmp_path / "matching_0ther").iterdir())) == 2  # the newer of the others
    # under a bound that no other kernel can meet, this installation's go too, oldest first
    assert prune_numba_cache(tmp_path, max_bytes=1000, keep={mine}) == 4


def test_an_empty_variable_counts_as_unset(tmp_path: Path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": "", "XDG_CACHE_HOME": str(tmp_path)}
    out = _run("import scanguard, os; print(os.environ['NUMBA_CACHE_DIR'])", env)
    assert out == str(tmp_path / "scanguard" / "numba")
