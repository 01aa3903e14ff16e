"""``dataset build`` on an executor (issue 13): shards, resume, corrupt shards, failures.

Every sequence (simulated) or recording is one task writing its own shard; the merged store
must equal the store of a plain in-process build of the same input exactly (every record
column, the scans, the manifest). Workers are real spawned processes (`LocalExecutor`); the
Ray variant runs only where Ray is installed.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from scanguard.cli import app
from scanguard.dataset import DatasetConfig, PairStore, build_dataset, merge_stores, tasks
from scanguard.dataset import build as build_mod
from scanguard.errors import InputError
from scanguard.runtime.executor import LocalExecutor, Outcome
from tests.test_hostile_data import write_corrected_log

CFG = DatasetConfig(gmapping_score=False)
#: The sequence whose worker is killed in the resume test.
VICTIM = "lobby_01"


def sim_config() -> DatasetConfig:
    """Four short simulated sequences (real simulator: the workers are other processes)."""
    return DatasetConfig.from_dict(
        {
            "name": "tiny-scale",
            "matcher": "icp-paper",
            "gmapping_score": False,
            "splits": {"val_sequences": 1, "test_sequences": 1, "seed": 3},
            "environments": [
                {"name": "lobby", "scenario": "lobby", "sequences": 3, "duration": 1.0, "seed": 0},
                {
                    "name": "office",
                    "scenario": "office",
                    "sequences": 1,
                    "duration": 1.0,
                    "seed": 100,
                    "heldout": True,
                },
            ],
        }
    )


def assert_same_store(a: Path, b: Path) -> None:
    """Identical arrays and labels, identical scans, identical manifest."""
    sa, sb = PairStore.open(a), PairStore.open(b)
    assert sa.records.keys() == sb.records.keys()
    for key in sa.records:
        np.testing.assert_array_equal(sa.records[key], sb.records[key], err_msg=key)
    np.testing.assert_array_equal(sa.labels, sb.labels)
    for i in range(len(sa)):
        for x, y in zip(sa.pair_points(i), sb.pair_points(i), strict=True):
            np.testing.assert_array_equal(x, y)
    ma, mb = (json.loads((d / "manifest.json").read_text()) for d in (a, b))
    for m in (ma, mb):
        m.pop("name")  # a recordings build is named after its folder
        for e in m["sequences"]:
            e.pop("recording", None)  # the absolute path differs between the two inputs
    assert ma == mb


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "local"
    s = build_dataset(sim_config(), out, progress=False)
    assert len(s.built) == 4 and s.complete and not s.failed
    return out


def test_two_workers_equal_the_local_build(reference: Path, tmp_path: Path) -> None:
    s = build_dataset(sim_config(), tmp_path / "two", progress=False, executor=LocalExecutor(2))
    assert sorted(s.built) == ["lobby_00", "lobby_01", "lobby_02", "office_00"]
    assert s.complete and not s.failed
    assert_same_store(reference, tmp_path / "two")


def test_ray_workers_equal_the_local_build(reference: Path, tmp_path: Path) -> None:
    pytest.importorskip("ray")
    from scanguard.runtime.executor import make_executor

    s = build_dataset(
        sim_config(), tmp_path / "ray", progress=False, executor=make_executor("ray", workers=2)
    )
    assert s.complete and not s.failed
    assert_same_store(reference, tmp_path / "ray")


def die_or_build(task: Any) -> dict[str, Any]:
    """The build task, except that the worker building `VICTIM` is killed (no clean-up)."""
    if task.item.sequence == VICTIM:
        os._exit(9)
    return tasks.sequence_task(task)


class KillingExecutor:
    """Two spawned workers; the one that gets `VICTIM` dies in the middle of its task."""

    def map(
        self, fn: Callable[[Any], Any], items: Iterable[Any]
    ) -> Iterator[tuple[Any, Outcome[Any]]]:
        assert fn is tasks.sequence_task
        return LocalExecutor(2).map(die_or_build, items)


def test_killed_worker_costs_only_its_shard_and_a_rerun_resumes(
    reference: Path, tmp_path: Path
) -> None:
    out = tmp_path / "killed"
    s = build_dataset(sim_config(), out, progress=False, executor=KillingExecutor())
    # it dies every time (also when run again in a process of its own); the tasks that
    # shared its pool ran again in processes of their own: only its shard is missing
    assert list(s.failed) == [VICTIM] and s.failed[VICTIM].startswith("worker failed")
    assert sorted(s.built) == ["lobby_00", "lobby_02", "office_00"] and not s.complete
    m = json.loads((out / "manifest.json").read_text())
    assert m["complete"] is False and m["pending"] == [{"sequence": VICTIM}]
    assert {e["sequence"] for e in m["sequences"]} == set(s.built)
    assert not (out / "sequences" / f"{VICTIM}.h5").exists()  # never a half-written shard
    # the rerun builds only what is missing and ends with the local build's data
    again = build_dataset(sim_config(), out, progress=False, executor=LocalExecutor(2))
    assert sorted(again.skipped) == sorted(s.built) and again.built == [VICTIM]
    assert again.complete and not again.failed
    assert_same_store(reference, out)


def test_corrupt_shard_is_refused_then_rebuilt(reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "corrupt"
    build_dataset(sim_config(), out, progress=False, executor=LocalExecutor(2))
    shard = out / "sequences" / "lobby_02.h5"
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])  # truncated: a disk or copy error
    # never merged silently: opening or merging the store names the shard
    with pytest.raises(InputError, match=r"lobby_02\.h5"):
        PairStore.open(out)
    with pytest.raises(InputError, match=r"lobby_02\.h5"):
        merge_stores([out], tmp_path / "merged")
    s = build_dataset(sim_config(), out, progress=False, executor=LocalExecutor(2))
    assert s.built == ["lobby_02"] and len(s.skipped) == 3
    assert_same_store(reference, out)


def test_failing_recording_is_reported_and_the_others_finish(tmp_path: Path) -> None:
    logs = [write_corrected_log(tmp_path / "in" / f"r{k}-corrected.log", seed=k) for k in range(3)]
    bad = tmp_path / "in" / "broken-corrected.log"
    bad.write_text("FLASER 181 garbage\n")
    inputs = [logs[0], bad, logs[1], logs[2]]
    # the reference: the good recordings one after the other, in this process
    build_mod.build_from_recordings(logs, tmp_path / "ref", CFG, progress=False)
    s = build_mod.build_from_recordings(
        inputs, tmp_path / "par", CFG, progress=False, executor=LocalExecutor(2)
    )
    assert list(s.failed) == [str(bad)] and "broken-corrected.log" in s.failed[str(bad)]
    assert s.built == ["r0-corrected", "r1-corrected", "r2-corrected"]
    m = json.loads((tmp_path / "par" / "manifest.json").read_text())
    assert m["complete"] is True and m["pending"] == []  # an unreadable file is not retried
    assert_same_store(tmp_path / "ref", tmp_path / "par")
    # the command line reports it, finishes the others, and exits 1; a rerun resumes
    cfg_path = tmp_path / "cfg.yaml"
    CFG.save(cfg_path)

    def build(paths: list[Path]) -> Any:
        args = [x for p in paths for x in ("-r", str(p))]
        out = ["-o", str(tmp_path / "cli"), "-c", str(cfg_path)]
        return CliRunner().invoke(app, ["dataset", "build", *args, *out])

    r = build(inputs)
    assert r.exit_code == 1, r.output
    assert "3 built, 0 resumed" in r.output and "broken-corrected.log" in r.output
    assert_same_store(tmp_path / "ref", tmp_path / "cli")
    r = build(logs)
    assert r.exit_code == 0, r.output
    assert "0 built, 3 resumed" in r.output
