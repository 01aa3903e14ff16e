"""Held-out protocol: every method's threshold comes from the selection pairs, by one rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.detect.protocol import evaluate_heldout
from scanguard.errors import ConfigError
from scanguard.scoring import choose_threshold


def test_thresholds_come_from_the_selection_pairs_not_the_evaluation_pairs():
    # selection: faults score >= 2, normals <= 1 -> the rule picks a threshold in (1, 2)
    sel_y = np.array([0, 0, 0, 1, 1, 1, -1])
    sel_s = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 9.0])
    # evaluation: a normal at 1.5 (passes at a threshold in (1, 2)) and a fault at 1.2 (missed)
    ev_y = np.array([0, 0, 1, 1, -1])
    ev_s = np.array([0.2, 1.5, 1.2, 5.0, 0.0])
    res = evaluate_heldout(ev_y, {"residual": ev_s}, sel_y, {"residual": sel_s}, calibrated=())
    row = res["residual"].row
    t = choose_threshold(sel_y, sel_s)
    assert row["threshold"] == t and 1.0 < t < 2.0
    # the flagged set depends on where in (1, 2) the rule put it; both cases are known answers
    flagged = ev_s[ev_y >= 0] >= t
    assert row["TP"] + row["FP"] == int(flagged.sum())
    assert row["n"] == 4 and row["n_selection"] == 6 and math.isnan(row["ece"])


def test_cnn_logits_are_platt_calibrated_on_selection_and_get_an_ece():
    rng = np.random.default_rng(0)
    y = rng.integers(0, 2, 4000)
    # class-conditional N(+-1.5, 1): the true log-odds are 3 * x; the model's logit is
    # z = 2 x + 1, so the calibrated logit is 1.5 z - 1.5 (a known answer)
    x = np.where(y == 1, 1.5, -1.5) + rng.normal(0, 1.0, y.size)
    z = 2.0 * x + 1.0
    sel, ev = slice(0, 2000), slice(2000, None)
    res = evaluate_heldout(y[ev], {"cnn": z[ev]}, y[sel], {"cnn": z[sel]})
    row = res["cnn"].row
    cal = row["calibration"]
    assert cal["method"] == "platt" and cal["a"] == pytest.approx(1.5, rel=0.15)
    assert cal["b"] == pytest.approx(-1.5, abs=0.3)
    assert row["ece"] < 0.05
    raw_ece = res["cnn"].row["ece"]
    assert raw_ece >= 0.0 and 0.0 <= res["cnn"].proba.min() <= res["cnn"].proba.max() <= 1.0
    assert row["balanced_accuracy"] > 0.9


def test_non_finite_scores_are_sure_faults_and_missing_methods_are_refused():
    res = evaluate_heldout(
        [1, 0], {"residual": [np.nan, 0.1]}, [0, 1], {"residual": [0.1, 0.9]}, calibrated=()
    )
    assert res["residual"].row["TP"] == 1 and res["residual"].row["TN"] == 1
    with pytest.raises(ConfigError, match="no selection scores"):
        evaluate_heldout([0, 1], {"cnn": [0.0, 1.0]}, [0, 1], {})
