from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from scanguard.detect.evaluate import MethodScores, evaluate_scores, write_results
from scanguard.scoring import confusion, roc_auc

# 10 pairs: labels, scores; hand-computed at threshold 0.5:
#   faults (1): scores 0.9 0.8 0.4 0.7   -> TP 3 (0.9 0.8 0.7), FN 1 (0.4)
#   normals (0): 0.1 0.6 0.2 0.3 0.05    -> FP 1 (0.6), TN 4
#   ambiguous (-1): 0.55 -> ignored by the confusion matrix
LABELS = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, -1])
SCORES = np.array([0.9, 0.8, 0.4, 0.7, 0.1, 0.6, 0.2, 0.3, 0.05, 0.55])
ENV = np.array(["a", "a", "b", "b", "a", "a", "b", "b", "b", "a"])


def test_confusion_matches_hand_computation() -> None:
    c = confusion(LABELS, SCORES, 0.5)
    assert (c["TP"], c["FN"], c["FP"], c["TN"], c["n"]) == (3, 1, 1, 4, 9)
    assert c["recall"] == pytest.approx(3 / 4)
    assert c["precision"] == pytest.approx(3 / 4)
    assert c["accuracy"] == pytest.approx(7 / 9)
    assert c["f1"] == pytest.approx(0.75)
    # AUC by pair counting over 4 x 5 (fault, normal) pairs: only 0.4 < 0.6 is ranked wrong
    assert c["auc"] == pytest.approx(19 / 20)


def test_threshold_is_inclusive_and_empty_rates_are_nan() -> None:
    c = confusion([1, 0], [0.5, 0.49], 0.5)
    assert (c["TP"], c["TN"]) == (1, 1)
    c = confusion([0, 0], [0.1, 0.2], 0.5)
    assert math.isnan(c["recall"]) and math.isnan(c["precision"]) and math.isnan(c["auc"])
    assert c["accuracy"] == 1.0
    assert math.isnan(roc_auc([1, 1], [0.2, 0.3]))


def test_table_per_environment_and_ambiguous(tmp_path: Path) -> None:
    res = evaluate_scores(
        LABELS,
        ENV,
        [MethodScores("cnn", SCORES, 0.5), MethodScores("const", np.zeros(10), 0.5)],
        meta={"model": "x"},
    )
    a = res.row("cnn", "a")  # faults .9 .8 ; normals .1 .6 ; ambiguous .55
    assert (a["TP"], a["FN"], a["FP"], a["TN"]) == (2, 0, 1, 1)
    b = res.row("cnn", "b")  # faults .4 .7 ; normals .2 .3 .05
    assert (b["TP"], b["FN"], b["FP"], b["TN"]) == (1, 1, 0, 3)
    allr = res.row("cnn")
    assert (allr["n_ambiguous"], allr["ambiguous_flagged"]) == (1, 1.0)
    assert res.row("const")["recall"] == 0.0
    assert math.isnan(res.row("cnn", "b")["ambiguous_flagged"])
    paths = write_results(res, tmp_path)
    data = json.loads(paths["json"].read_text())
    assert data["positive_class"] == "fault"
    assert len(data["rows"]) == 6
    assert data["rows"][1]["ambiguous_flagged"] is None  # NaN -> null
    rows = list(csv.DictReader(io.StringIO(paths["csv"].read_text())))
    assert rows[2]["environment"] == "all" and rows[2]["TP"] == "3"
    for key in ("roc", "confusion_cnn", "confusion_const"):
        assert paths[key].stat().st_size > 1000


# --- evaluate_store on a small labelled store ---------------------------------------------


class _ErrorMatcher:
    """Returns the reference step composed with a known error; residual grows with it."""

    def __init__(self, steps: list[np.ndarray], errors: list[np.ndarray]) -> None:
        self.steps, self.errors, self.k = steps, errors, 0

    def __call__(self, source, target, initial=None):  # type: ignore[no-untyped-def]
        from scanguard.geometry import compose
        from scanguard.matching.result import MatchResult

        err = self.errors[self.k]
        pose = compose(self.steps[self.k], err)
        self.k += 1
        mag = float(np.hypot(err[0], err[1]) + abs(err[2]))
        return MatchResult(
            pose=pose,
            iterations=3,
            converged=True,
            reason="converged",
            mean_residual=0.01 + mag,
            median_residual=0.01 + mag,
            inlier_ratio=max(0.0, 0.95 - mag),
            inlier_threshold=0.1,
            n_source=len(source),
            n_target=len(target),
            n_inliers=len(source),
        )


def write_injected_sequence(
    out: Path, k: int, step_seed: int, split: str, environment: str, fault: float
) -> Path:
    """Write pair file ``s<k>.h5``: 13 scans whose matches cycle through normal, a ``fault`` m
    error, normal and ambiguous (0.085 m), labelled against the exact reference."""
    from scanguard.dataset import label_sequence, write_sequence_file
    from scanguard.pairs.labels import LabelConfig
    from tests.helpers import small_room_walk
    from tests.test_model import SMALL_SENSOR

    n = 13
    seq, true = small_room_walk(step_seed, k, n, SMALL_SENSOR)
    cycle = [[0, 0, 0], [fault, 0, 0], [0.002, 0, 0], [0.085, 0, 0]]
    errs = [np.array(cycle[i % 4], float) for i in range(n - 1)]
    rec = label_sequence(
        seq,
        environment=environment,
        sequence=f"s{k}",
        split=split,
        matcher=_ErrorMatcher(true, errs),
        matcher_name="inject",
        initial_guess="identity",
        labels=LabelConfig(),
        gmapping=False,
    )
    return write_sequence_file(out / f"s{k}.h5", rec)


@pytest.fixture(scope="module")
def small_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("store")
    for k, split in enumerate(["train", "test"]):
        write_injected_sequence(out, k, 40 + k, split, "room" if k == 0 else "hall", 0.5)
    return out


@pytest.fixture(scope="module")
def random_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import torch

    from scanguard.detect.checkpoint import make_checkpoint, save_checkpoint
    from scanguard.detect.model import build_model

    torch.manual_seed(0)
    ck = make_checkpoint(
        build_model("tiny"), style={"kind": "occupancy", "size": 32}, threshold=0.5
    )
    return save_checkpoint(ck, tmp_path_factory.mktemp("m") / "model.pt")


def test_evaluate_store_cnn_matches_detector_and_baselines_fit_on_train(
    small_store: Path, random_model: Path, tmp_path: Path
) -> None:
    from scanguard.dataset import PairStore
    from scanguard.detect.detector import FaultDetector
    from scanguard.detect.evaluate import best_baseline, evaluate_store

    ps = PairStore.open(sorted(small_store.glob("*.h5")))
    res = evaluate_store(
        random_model, ps, tmp_path, splits=["test"], baselines=["residual", "overlap"]
    )
    test_idx = ps.indices("test", include_ambiguous=True)
    labels = np.asarray(ps.records["label"])[test_idx]
    assert sorted(set(labels.tolist())) == [-1, 0, 1]
    det = FaultDetector.load(random_model)
    scans = [ps.pair_scans(int(i)) for i in test_idx]
    p = det.predict_pairs([s[0] for s in scans], [s[1] for s in scans], [s[2] for s in scans])
    want = confusion(labels, p, det.threshold)
    got = res.row("cnn", "hall")
    for k in ("TP", "FN", "FP", "TN", "n"):
        assert got[k] == want[k], k
    assert got["n_ambiguous"] == int((labels == -1).sum())
    # the residual baseline is perfectly separable by construction (fitted on the train file)
    r = res.row("residual")
    assert (r["FN"], r["FP"], r["accuracy"]) == (0, 0, 1.0)
    assert best_baseline(res) in ("residual", "overlap")
    assert {m.name for m in res.methods} == {"cnn", "residual", "overlap"}
    assert (tmp_path / "results.json").is_file() and (tmp_path / "roc.png").is_file()


def test_cli_evaluate_and_export(small_store: Path, random_model: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from scanguard.cli import app

    runner = CliRunner()
    out = tmp_path / "ev"
    r = runner.invoke(
        app,
        [
            "evaluate",
            "-d",
            str(small_store / "s0.h5"),
            "-d",
            str(small_store / "s1.h5"),
            "-m",
            str(random_model),
            "-o",
            str(out),
            "--split",
            "test",
            "--baselines",
            "residual",
        ],
    )
    assert r.exit_code == 0, r.output
    assert "positive class: fault" in r.output and "residual" in r.output
    data = json.loads((out / "results.json").read_text())
    assert {row["method"] for row in data["rows"]} == {"cnn", "residual"}
    r = runner.invoke(
        app, ["export", "onnx", "-m", str(random_model), "-o", str(tmp_path / "x.onnx")]
    )
    assert r.exit_code == 0, r.output
    assert (tmp_path / "x.onnx").stat().st_size > 1000
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    r = runner.invoke(app, ["export", "onnx", "-m", str(bad), "-o", str(tmp_path / "y.onnx")])
    assert r.exit_code == 1
    assert "bad.pt" in r.output


def test_evaluate_store_hybrid_cnn_reads_store_metrics(small_store: Path, tmp_path: Path) -> None:
    import torch

    from scanguard.dataset import PairStore
    from scanguard.detect.checkpoint import make_checkpoint, save_checkpoint
    from scanguard.detect.detector import FaultDetector
    from scanguard.detect.evaluate import evaluate_store
    from scanguard.detect.features import store_features
    from scanguard.detect.images import render_all
    from scanguard.detect.model import build_model, get_preset, metric_inputs

    names = ["mean_residual", "inlier_ratio", "iterations"]
    torch.manual_seed(1)
    model = build_model(get_preset("tiny").model_copy(update={"metrics": names}))
    ck = make_checkpoint(model, style={"kind": "occupancy", "size": 32}, threshold=0.5)
    path = save_checkpoint(ck, tmp_path / "hybrid.pt")
    ps = PairStore.open(sorted(small_store.glob("*.h5")))
    res = evaluate_store(path, ps, None, splits=["test"], baselines=[])
    idx = ps.indices("test", include_ambiguous=True)
    det = FaultDetector.load(path)
    imgs = torch.from_numpy(render_all(ps, idx, det.style)).permute(0, 3, 1, 2).float() / 255
    met = torch.from_numpy(metric_inputs(store_features(ps, idx), names))
    p = det.model.fault_probability(imgs, met).numpy()
    got = res.methods[0]
    assert got.name == "cnn"
    np.testing.assert_allclose(got.scores, p, atol=1e-6)
