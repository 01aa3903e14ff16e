"""Scores of a binary detector: one module that every stage uses.

Fault (label 1) is the positive class; label 0 is normal; any other label (ambiguous, -1) is
ignored. A pair is flagged when ``score >= threshold``.

* `balanced_accuracy`, `confusion`, `roc_auc`: figures at an operating point.
* `choose_threshold`: the project's threshold rule (maximum balanced accuracy over the
  midpoints between distinct scores, ties broken towards 0.5), used for the CNN, the classical
  detectors and the closure judge alike; `metric_threshold`: the training loop's rule for a
  named metric (accuracy, f1, fixed).
* `reliability`, `expected_calibration_error`: calibration of probabilities (15 equal-width
  bins, weighted by bin counts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import ConfigError

#: Number of equal-width probability bins of the ECE and the reliability diagram.
ECE_BINS = 15


#: Balanced accuracies closer than this are ties (see `choose_threshold`).
TIE_TOLERANCE = 1e-12


def sigmoid(z: ArrayLike) -> NDArray[np.float64]:
    """Numerically stable logistic function (float64)."""
    x = np.asarray(z, dtype=np.float64)
    out = np.empty_like(x)
    pos = x >= 0
    out[pos] = 1.0 / (1.0 + np.exp(-x[pos]))
    e = np.exp(x[~pos])
    out[~pos] = e / (1.0 + e)
    return out


def labelled(labels: ArrayLike, values: ArrayLike, what: str) -> tuple[NDArray[Any], ...]:
    """Labels 0/1 and the matching finite values (ambiguous and non-finite pairs dropped)."""
    y = np.asarray(labels).reshape(-1)
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if y.shape != v.shape:
        raise ConfigError(f"{what}: {y.size} labels but {v.size} values")
    keep = ((y == 0) | (y == 1)) & np.isfinite(v)
    return y[keep].astype(np.int64), v[keep]


def balanced_accuracy(labels: ArrayLike, scores: ArrayLike, threshold: float) -> float:
    """Mean of the fault recall and the normal recall at ``score >= threshold`` (NaN: one class)."""
    y, s = labelled(labels, scores, "balanced_accuracy")
    if y.size == 0 or y.all() or not y.any():
        return math.nan
    pred = s >= threshold
    yb = y.astype(bool)
    return float(0.5 * (np.mean(pred[yb]) + np.mean(~pred[~yb])))


def choose_threshold(labels: ArrayLike, proba: ArrayLike) -> float:
    """The operating threshold by the module's rule (max balanced accuracy, ties -> 0.5).

    Args:
        labels: 0 / 1 per pair (others ignored).
        proba: Calibrated fault probability per pair.

    Returns:
        The threshold (0.5 when a class is missing).
    """
    y, p = labelled(labels, proba, "choose_threshold")
    if y.size == 0 or y.all() or not y.any():
        return 0.5
    u = np.unique(p)
    cands = np.concatenate([[0.5], (u[:-1] + u[1:]) / 2]) if len(u) > 1 else np.array([0.5])
    order = np.argsort(p, kind="stable")
    ps, ys = p[order], y[order].astype(bool)
    n_pos, n_neg = int(ys.sum()), int((~ys).sum())
    # pairs with p < t: the first searchsorted(ps, t, "left") of the sorted list
    below = np.searchsorted(ps, cands, side="left")
    pos_below = np.concatenate([[0], np.cumsum(ys)])[below]
    neg_below = below - pos_below
    bal = 0.5 * ((n_pos - pos_below) / n_pos + neg_below / n_neg)
    best = float(bal.max())
    tied = np.flatnonzero(bal >= best - TIE_TOLERANCE)
    pick = tied[np.argmin(np.abs(cands[tied] - 0.5))]
    return float(cands[pick])


@dataclass
class Reliability:
    """Per-bin statistics of a reliability diagram.

    Attributes:
        edges: ``(bins + 1,)`` bin edges on [0, 1].
        count: Pairs per bin.
        confidence: Mean predicted fault probability per bin (NaN when empty).
        frequency: Observed fault frequency per bin (NaN when empty).
        ece: Expected calibration error.
    """

    edges: NDArray[np.float64]
    count: NDArray[np.int64]
    confidence: NDArray[np.float64]
    frequency: NDArray[np.float64]
    ece: float


def reliability(labels: ArrayLike, proba: ArrayLike, bins: int = ECE_BINS) -> Reliability:
    """Reliability statistics and ECE (see the module docstring for the binning)."""
    y, p = labelled(labels, proba, "reliability")
    p = np.clip(p, 0.0, 1.0)
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.minimum((p * bins).astype(np.int64), bins - 1)
    count = np.bincount(idx, minlength=bins).astype(np.int64)
    sum_p = np.bincount(idx, weights=p, minlength=bins)
    sum_y = np.bincount(idx, weights=y.astype(np.float64), minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        conf = np.where(count > 0, sum_p / np.maximum(count, 1), np.nan)
        freq = np.where(count > 0, sum_y / np.maximum(count, 1), np.nan)
    n = int(count.sum())
    ece = (
        float(np.sum(np.abs(sum_p - sum_y)) / n)  # = sum_k n_k / n * |conf_k - freq_k|
        if n
        else math.nan
    )
    return Reliability(edges, count, conf, freq, ece)


def expected_calibration_error(labels: ArrayLike, proba: ArrayLike, bins: int = ECE_BINS) -> float:
    """ECE with ``bins`` equal-width bins, weighted by bin counts (NaN: no labelled pair)."""
    return reliability(labels, proba, bins).ece


def confusion(
    labels: ArrayLike, scores: ArrayLike, threshold: float = 0.5
) -> dict[str, float | int]:
    """Confusion counts and rates with fault (label 1) as the positive class.

    Args:
        labels: 0 (normal) / 1 (fault) per pair; other values (ambiguous) are ignored.
        scores: Fault score per pair (higher = more likely a fault).
        threshold: A pair is flagged as fault when ``score >= threshold``.

    Returns:
        ``n, TP, FN, FP, TN, recall, precision, accuracy, balanced_accuracy, f1, auc,
        threshold``; rates whose denominator is zero are NaN, ``auc`` and
        ``balanced_accuracy`` are NaN unless both classes are present.
    """
    y = np.asarray(labels).reshape(-1)
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if y.shape != s.shape:
        raise ConfigError(f"confusion: {y.size} labels but {s.size} scores")
    keep = (y == 0) | (y == 1)
    y, s = y[keep].astype(bool), s[keep]
    pred = s >= threshold
    tp = int(np.sum(pred & y))
    fn = int(np.sum(~pred & y))
    fp = int(np.sum(pred & ~y))
    tn = int(np.sum(~pred & ~y))

    def ratio(a: int, b: int) -> float:
        return a / b if b else math.nan

    recall = ratio(tp, tp + fn)
    precision = ratio(tp, tp + fp)
    f1 = ratio(2 * tp, 2 * tp + fp + fn)
    specificity = ratio(tn, tn + fp)
    return {
        "n": int(y.size),
        "TP": tp,
        "FN": fn,
        "FP": fp,
        "TN": tn,
        "recall": recall,
        "precision": precision,
        "accuracy": ratio(tp + tn, int(y.size)),
        "balanced_accuracy": 0.5 * (recall + specificity),
        "f1": f1,
        "auc": roc_auc(y, s),
        "threshold": float(threshold),
    }


def roc_auc(labels: ArrayLike, scores: ArrayLike) -> float:
    """Area under the ROC curve (NaN when only one class is present)."""
    y = np.asarray(labels).astype(bool).reshape(-1)
    if y.all() or not y.any():
        return math.nan
    from sklearn.metrics import roc_auc_score

    return float(roc_auc_score(y, np.asarray(scores, dtype=np.float64)))


def metric_threshold(
    labels: NDArray[np.int64], proba: NDArray[np.float64], metric: str = "accuracy"
) -> float:
    """Operating threshold on fault probability (predict fault when ``p >= threshold``).

    Candidates are midpoints between sorted distinct scores; ties prefer the threshold
    closest to 0.5 so that an uninformative search keeps the natural decision rule.
    """
    if metric == "fixed" or len(labels) == 0 or len(np.unique(labels)) < 2:
        return 0.5
    p = np.unique(proba)
    cands = np.concatenate([[0.5], (p[:-1] + p[1:]) / 2]) if len(p) > 1 else np.array([0.5])
    y = labels.astype(bool)
    best, best_t = -1.0, 0.5
    for t in cands[np.argsort(np.abs(cands - 0.5), kind="stable")]:
        pred = proba >= t
        if metric == "f1":
            tp = float(np.sum(pred & y))
            denom = float(np.sum(pred) + np.sum(y))
            score = 2 * tp / denom if denom else 0.0
        else:
            score = float(np.mean(pred == y))
        if score > best + 1e-12:
            best, best_t = score, float(t)
    return best_t
