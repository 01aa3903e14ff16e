"""Executors and ``scanguard run-many`` (issue 13): order, failure isolation, resume, table."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from scanguard.apps.run_many import RecordingResult, find_recordings, recording_stem, result_row
from scanguard.cli import app
from scanguard.errors import ConfigError
from scanguard.fsutil import read_marker
from scanguard.runtime.executor import LocalExecutor, make_executor

DATA = Path(__file__).parent / "data"
GOOD = ("intel-corrected-excerpt.log.gz", "ccny-excerpt.bag")


def square_or_fail(x: int) -> int:
    """Top-level (spawn-safe) task: fails for 3."""
    if x == 3:
        raise ValueError("three is\nnot allowed")
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_local_executor_order_and_isolation(workers: int) -> None:
    items = [5, 3, 1, 4, 2]
    got = list(LocalExecutor(workers).map(square_or_fail, items))
    assert [item for item, _ in got] == items
    for item, outcome in got:
        if item == 3:
            assert not outcome.ok
            assert outcome.value is None
            assert outcome.error == "ValueError: three is not allowed"  # one line
        else:
            assert outcome.ok and outcome.value == item * item


def test_make_executor_checks() -> None:
    with pytest.raises(ConfigError, match="only used with --executor ray"):
        make_executor("local", address="10.0.0.1:6379")
    with pytest.raises(ConfigError, match="--executor must be one of"):
        make_executor("dask")
    with pytest.raises(ConfigError, match="--workers must be >= 1"):
        make_executor("local", workers=0)


def test_ray_executor_missing_or_present() -> None:
    try:
        import ray  # noqa: F401
    except ImportError:
        with pytest.raises(ConfigError) as info:
            make_executor("ray")
        assert str(info.value) == (
            "--executor ray needs the optional extra: pip install 'scanguard[scale]'"
        )
    else:
        pytest.importorskip("ray")
        ex = make_executor("ray", workers=2)
        got = list(ex.map(square_or_fail, [2, 3]))
        assert got[0][1].value == 4 and got[1][1].error == "ValueError: three is not allowed"


def test_ray_executor_runs() -> None:
    pytest.importorskip("ray")
    got = list(make_executor("ray", workers=2).map(square_or_fail, [1, 2, 3]))
    assert [o.value for _, o in got[:2]] == [1, 4] and not got[2][1].ok


def test_find_recordings(tmp_path: Path) -> None:
    for name in GOOD:
        (tmp_path / "sub").mkdir(exist_ok=True)
        (tmp_path / "sub" / name).write_bytes(b"x")
    (tmp_path / "notes.txt").write_text("not a recording")
    (tmp_path / "intel.relations").write_text("")
    found = find_recordings(tmp_path)
    assert [p.name for p in found] == sorted(GOOD)
    assert [recording_stem(p) for p in found] == ["ccny-excerpt", "intel-corrected-excerpt"]
    assert [p.name for p in find_recordings(str(tmp_path / "**" / "*.bag"))] == [GOOD[1]]
    (tmp_path / "ccny-excerpt.log").write_text("x")
    with pytest.raises(Exception, match="same name 'ccny-excerpt'"):
        find_recordings(tmp_path)
    with pytest.raises(Exception, match="no recordings found"):
        find_recordings(tmp_path / "sub" / "*.clf")


def test_result_row_relations_and_failure() -> None:
    metrics = {
        "n_scans": 7,
        "odometry_source": "recorded",
        "backend": "gmapping",
        "matcher": "icp-paper",
        "counts": {"accepted": 5, "rejected": 1},
        "latency_ms": {"guard total": {"median": 1.25, "p95": 3.0}},
        "errors": {},
        "relations": {
            "all": {"gmapping": {"trans_mean": 0.125, "rot_mean_deg": 0.5}},
            "dt <= 10 s": {"gmapping": {"trans_mean": 9.0, "rot_mean_deg": 9.0}},
        },
    }
    row = result_row(RecordingResult(Path("a.clf"), Path("out/a"), "ok", metrics))
    assert row["rel_trans_mean[gmapping]"] == 0.125  # all relations, not the short ones
    assert row["rel_rot_mean_deg[gmapping]"] == 0.5
    assert row["guard_latency_median_ms"] == 1.25
    assert (row["accepted"], row["rejected"], row["scans"]) == (5, 1, 7)
    failed = result_row(RecordingResult(Path("b.log"), Path("out/b"), "failed", error="bad"))
    assert failed["status"] == "failed" and failed["error"] == "bad"


@pytest.fixture(scope="module")
def many(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("many")
    src = root / "in"
    src.mkdir()
    for name in GOOD:
        shutil.copy(DATA / name, src / name)
    (src / "corrupt.log").write_text("garbage \x00 not a log\n" * 3)
    out = root / "out"
    args = ["run-many", str(src), "-o", str(out), "--backend", "frontend", "--max-scans", "20"]
    first = CliRunner().invoke(app, args)
    return {"src": src, "out": out, "args": args, "first": first}


def _table(out: Path) -> dict[str, dict[str, str]]:
    with (out / "results.csv").open() as f:
        return {Path(r["recording"]).name: r for r in csv.DictReader(f)}


def _num(text: str) -> float | int | None:
    if text == "":
        return None
    return int(text) if text.lstrip("-").isdigit() else float(text)


def test_run_many_table_matches_metrics(many: dict[str, Any]) -> None:
    first, out = many["first"], many["out"]
    assert first.exit_code == 1, first.output  # one recording failed
    assert "1 of 3 recordings failed" in first.output
    table = _table(out)
    assert set(table) == {*GOOD, "corrupt.log"}
    bad = table["corrupt.log"]
    assert bad["status"] == "failed"
    assert "corrupt.log" in bad["error"] and "\n" not in bad["error"]
    assert not (out / "corrupt").exists()
    for name in GOOD:
        row = table[name]
        assert row["status"] == "ok"
        m = json.loads((out / recording_stem(name) / "metrics.json").read_text())
        assert _num(row["scans"]) == m["n_scans"] == 20
        assert row["odometry"] == m["odometry_source"]
        assert row["backend"] == m["backend"] == "frontend"
        assert row["matcher"] == m["matcher"]
        assert _num(row["accepted"]) == m["counts"]["accepted"]
        assert _num(row["rejected"]) == m["counts"]["rejected"]
        assert _num(row["guard_latency_median_ms"]) == m["latency_ms"]["guard total"]["median"]
        for traj, err in m["errors"].items():
            assert _num(row[f"ate_rmse[{traj}]"]) == err["ate_rmse"]
            assert _num(row[f"rpe_trans_rmse[{traj}]"]) == err["rpe_trans_rmse"]
        marker = read_marker(out / recording_stem(name))
        assert marker is not None
        assert marker["complete"] is True and marker["name"] == "scanguard run"
    # the intel excerpt has a reference: ATE/RPE per trajectory are in the table
    assert table[GOOD[0]]["ate_rmse[frontend+cnn]"] != ""
    md = (out / "results.md").read_text()
    assert "1 failed" in md and "ccny-excerpt.bag" in md
    assert any("corrupt.log | failed" in line for line in md.splitlines())


def test_run_many_resumes(many: dict[str, Any]) -> None:
    out = many["out"]
    before = {n: (out / recording_stem(n) / "metrics.json").stat().st_mtime_ns for n in GOOD}
    again = CliRunner().invoke(app, many["args"])
    assert again.exit_code == 1, again.output
    table = _table(out)
    for name in GOOD:
        assert table[name]["status"] == "resumed"
        after = (out / recording_stem(name) / "metrics.json").stat().st_mtime_ns
        assert after == before[name]  # not recomputed
    assert table["corrupt.log"]["status"] == "failed"  # retried, fails again


def test_run_many_ray_missing(tmp_path: Path) -> None:
    try:
        import ray  # noqa: F401

        pytest.skip("ray is installed")
    except ImportError:
        pass
    res = CliRunner().invoke(
        app, ["run-many", str(DATA), "-o", str(tmp_path / "o"), "--executor", "ray"]
    )
    assert res.exit_code == 1
    assert "--executor ray needs the optional extra: pip install 'scanguard[scale]'" in (res.output)
    assert not (tmp_path / "o").exists()
