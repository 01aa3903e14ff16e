"""Held-out evaluation with a fair threshold for every method.

Every figure of the model card comes from this one protocol. For a set of *evaluation* pairs
and a disjoint set of *selection* pairs (data used neither for training nor for the figure):

* the CNN's fault logit is calibrated on the selection pairs (Platt scaling by default,
  `scanguard.detect.calibrate.fit_calibration`) and its operating threshold is chosen there
  by the project's rule (`scanguard.scoring.choose_threshold`: maximum balanced
  accuracy, ties to the threshold nearest 0.5);
* every classical detector's score gets its threshold from the **same** selection pairs by
  the **same** rule, so the comparison is against the best threshold a careful user could pick
  from the same labelled data, not against a default;
* the evaluation pairs then give accuracy, balanced accuracy, recall, precision, F1, ROC AUC
  and, for calibrated probabilities, the expected calibration error (ECE).

Ambiguous pairs (label -1) take part in nothing.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.detect.calibrate import Method, fit_calibration
from scanguard.errors import ConfigError
from scanguard.scoring import choose_threshold, confusion, expected_calibration_error

__all__ = ["HeldOutResult", "evaluate_heldout"]

log = logging.getLogger(__name__)


@dataclass
class HeldOutResult:
    """One method on one held-out evaluation set.

    Attributes:
        method: Method name.
        row: `scanguard.scoring.confusion` of the evaluation pairs at the selected
            threshold, plus ``ece`` (NaN for an uncalibrated score), ``n_selection`` and
            ``calibration`` (the CNN's fitted block, else None).
        proba: The evaluation pairs' (calibrated) fault scores, for plots.
    """

    method: str
    row: dict[str, Any]
    proba: NDArray[np.float64]


def _labelled(labels: ArrayLike) -> NDArray[np.int64]:
    return np.asarray(labels, dtype=np.int64).reshape(-1)


def _fail_safe(scores: ArrayLike) -> NDArray[np.float64]:
    # a non-finite score (a failed match's NaN residual) is a sure fault, as the guard treats
    # it; it becomes a finite score above every other one so that ROC AUC stays defined
    s = np.asarray(scores, dtype=np.float64).reshape(-1).copy()
    bad = ~np.isfinite(s)
    if bad.any():
        finite = s[~bad]
        s[bad] = (float(finite.max()) if finite.size else 0.0) + 1.0
    return s


def evaluate_heldout(
    eval_labels: ArrayLike,
    eval_scores: Mapping[str, ArrayLike],
    select_labels: ArrayLike,
    select_scores: Mapping[str, ArrayLike],
    *,
    calibrated: tuple[str, ...] = ("cnn",),
    method: Method = "platt",
) -> dict[str, HeldOutResult]:
    """Evaluate every method on held-out pairs with its threshold chosen on selection pairs.

    Args:
        eval_labels: 0 / 1 / -1 per evaluation pair.
        eval_scores: Fault score per evaluation pair, by method (for ``calibrated`` methods:
            the fault logit margin).
        select_labels: 0 / 1 / -1 per selection pair (disjoint from the evaluation pairs).
        select_scores: The same methods' scores of the selection pairs.
        calibrated: Methods whose score is a logit to calibrate (ECE is reported for them).
        method: Calibration method of those.

    Returns:
        `HeldOutResult` by method, in the order of ``eval_scores``.

    Raises:
        ConfigError: A method misses its selection scores, or lengths disagree.
    """
    y_eval = _labelled(eval_labels)
    y_sel = _labelled(select_labels)
    out: dict[str, HeldOutResult] = {}
    for name, raw in eval_scores.items():
        if name not in select_scores:
            raise ConfigError(f"held-out evaluation: no selection scores for {name!r}")
        s_eval = _fail_safe(raw)
        s_sel = _fail_safe(select_scores[name])
        if s_eval.size != y_eval.size or s_sel.size != y_sel.size:
            raise ConfigError(
                f"held-out evaluation of {name!r}: {s_eval.size} scores for {y_eval.size} "
                f"pairs, {s_sel.size} selection scores for {y_sel.size} pairs"
            )
        block = None
        if name in calibrated:
            fit = fit_calibration(y_sel, s_sel, method=method, fitted_on="selection pairs")
            cal = fit.calibration
            p_eval = cal.apply(s_eval)
            threshold = cal.threshold
            ece = expected_calibration_error(y_eval, p_eval)
            block = cal.to_dict()
        else:
            # the same rule on the raw score: a monotone score needs no calibration to rank
            p_eval = s_eval
            threshold = choose_threshold(y_sel, s_sel)
            ece = math.nan
        row: dict[str, Any] = dict(confusion(y_eval, p_eval, threshold))
        row["ece"] = ece
        row["n_selection"] = int(np.sum((y_sel == 0) | (y_sel == 1)))
        row["calibration"] = block
        out[name] = HeldOutResult(name, row, p_eval)
    return out
