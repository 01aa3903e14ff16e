from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from scanguard.evaluate import (
    MethodScores,
    confusion,
    evaluate_scores,
    roc_auc,
    write_results,
)

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
