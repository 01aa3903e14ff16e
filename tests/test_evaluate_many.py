"""``scanguard evaluate --per-store`` (issue 13): one task per store, merged table, resume.

Known answer: every row of the merged ``results.csv`` equals the row that `evaluate_store`
gives for that store alone; a store that cannot be read is reported and the others finish.
"""

from __future__ import annotations

import csv
import json
import math
import pickle
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from scanguard.apps.evaluate_many import EvaluateTask, evaluate_many
from scanguard.cli import app
from scanguard.dataset import DatasetConfig
from scanguard.dataset.build import build_from_recordings
from scanguard.detect.evaluate import COLUMNS, evaluate_store
from scanguard.detect.train import train_images
from scanguard.detect.train_config import TrainConfig
from scanguard.runtime.executor import LocalExecutor
from tests.test_hostile_data import write_corrected_log
from tests.test_train import _images

CFG = DatasetConfig(gmapping_score=False)
STYLE = {"kind": "occupancy", "size": 32}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("many")
    cfg = TrainConfig.from_dict(
        {"preset": "tiny", "style": STYLE, "epochs": 1, "patience": 0, "seed": 0, "threads": 1}
    )
    train_images(cfg, _images(64, seed=1), _images(32, seed=2), root / "model")
    stores = []
    for k in range(2):
        logs = [
            write_corrected_log(root / f"in{k}" / f"w{k}{j}-corrected.log", seed=10 * k + j, n=8)
            for j in range(2)
        ]
        build_from_recordings(logs, root / f"store{k}", CFG, progress=False)
        stores.append(root / f"store{k}")
    broken = root / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_text("{not json")
    return {"model": str(root / "model" / "model.pt"), "stores": stores, "broken": broken}


OPTIONS = {"splits": ["heldout"], "baselines": [], "backend": "torch"}


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def _same(csv_value: str, value: Any) -> bool:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return csv_value in ("", "nan")
    if isinstance(value, float):
        return float(csv_value) == value
    return csv_value == str(value)


def test_merged_table_equals_each_store_alone(inputs: dict[str, Any], tmp_path: Path) -> None:
    stores = [inputs["stores"][0], inputs["broken"], inputs["stores"][1]]
    out = tmp_path / "ev"
    res = evaluate_many(stores, out, LocalExecutor(1), model=inputs["model"], **OPTIONS)
    assert [r.status for r in res] == ["ok", "failed", "ok"]
    assert "manifest.json" in str(res[1].error)
    rows = _csv_rows(out / "results.csv")
    assert list(rows[0]) == ["store", "status", *COLUMNS, "error"]
    for store in inputs["stores"]:
        alone = evaluate_store(inputs["model"], store, **OPTIONS).rows
        got = [r for r in rows if r["store"] == str(store)]
        assert [r["environment"] for r in got] == [r["environment"] for r in alone]
        for g, a in zip(got, alone, strict=True):
            assert g["status"] == "ok"
            for col in COLUMNS:
                assert _same(g[col], a[col]), (store, col, g[col], a[col])
        assert json.loads((out / store.name / "results.json").read_text())["rows"]
    failed = [r for r in rows if r["status"] == "failed"]
    assert len(failed) == 1 and failed[0]["store"] == str(inputs["broken"])
    # a rerun resumes the finished stores and retries the failed one
    again = evaluate_many(stores, out, LocalExecutor(1), model=inputs["model"], **OPTIONS)
    assert [r.status for r in again] == ["resumed", "failed", "resumed"]
    assert [r.rows for r in again] == [r.rows for r in res]


def test_evaluate_task_travels_to_a_worker(inputs: dict[str, Any], tmp_path: Path) -> None:
    # what a process pool or Ray sends: the task pickles, with a model path (not a model)
    task = EvaluateTask(inputs["stores"][0], tmp_path / "x", {"model": inputs["model"], **OPTIONS})
    assert pickle.loads(pickle.dumps(task)) == task


def test_cli_per_store(inputs: dict[str, Any], tmp_path: Path) -> None:
    args = ["evaluate", "-m", inputs["model"], "-s", "heldout", "--baselines", "none"]
    for s in inputs["stores"]:
        args += ["-d", str(s)]
    r = CliRunner().invoke(app, [*args, "--per-store", "-o", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    rows = _csv_rows(tmp_path / "ev" / "results.csv")
    assert {r["store"] for r in rows} == {str(s) for s in inputs["stores"]}
    assert (tmp_path / "ev" / "results.md").read_text().startswith("# scanguard evaluate")
    r = CliRunner().invoke(app, [*args, "--executor", "ray", "-o", str(tmp_path / "x")])
    assert r.exit_code != 0 and "--per-store" in r.output
