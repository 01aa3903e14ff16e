"""Fitting the loop-closure judges shipped in ``models/closure_judge.json``.

`fit_learned_judge` fits the learned judge
(`scanguard.slam.graph.judges.LearnedClosureJudge`, a `MetricsModelDetector` over the
candidate features). Its threshold follows the project's rule
(`scanguard.scoring.choose_threshold`: max balanced accuracy) on **validation**
probabilities: out-of-fold predictions with the training groups (sequences) left out one at a
time, never the data the final model is fitted on and never the test data. The model kind
(``gbm`` or ``logistic``) is chosen on the same out-of-fold predictions.

`fit_classical` fits the classical test a careful user would configure
(`scanguard.slam.graph.judges.ClassicalClosureTest`): Karto's minimum response and maximum
standard deviations plus a maximum-disagreement gate (how far the closure moves the graph), by
a grid search and coordinate ascent maximising the balanced accuracy on the training
candidates.

The training candidates come from `scanguard.apps.closure_harvest`; the fitted pair is written
with `scanguard.slam.graph.judges.save_closure_judge` (``benchmarks/closure_judge.py`` runs
the whole recipe).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.apps.closure_harvest import candidate_table
from scanguard.detect.baselines.metrics_model import MetricsModelDetector
from scanguard.errors import ModelError
from scanguard.scoring import balanced_accuracy, choose_threshold
from scanguard.slam.graph.judges import (
    CLASSICAL_FEATURES,
    LEARNED_FEATURES,
    ClassicalClosureTest,
    LearnedClosureJudge,
)

logger = logging.getLogger(__name__)

THRESHOLD_RULE = (
    "scanguard.scoring.choose_threshold (max balanced accuracy) on out-of-fold "
    "validation probabilities (leave-one-sequence-out over the training sequences)"
)


CLASSICAL_RULE = (
    "grid search + coordinate ascent maximising balanced accuracy on the training candidates"
)


Kind = Literal["gbm", "logistic"]


# (column, direction): "min" = pass when value >= t, "max" = pass when value <= t
_CLASSICAL_DIRS: tuple[tuple[str, str], ...] = (
    ("response", "min"),
    ("std_xy", "max"),
    ("std_theta", "max"),
    ("disagreement_m", "max"),
    ("disagreement_rad", "max"),
)


def _bal_acc(reject: NDArray[np.bool_], fault: NDArray[np.bool_]) -> float:
    """Balanced accuracy of 'reject = predicted fault'."""
    tpr = float(reject[fault].mean()) if fault.any() else 0.0
    tnr = float((~reject[~fault]).mean()) if (~fault).any() else 0.0
    return 0.5 * (tpr + tnr)


def _candidates(values: NDArray[np.float64], direction: str) -> NDArray[np.float64]:
    """Thresholds worth trying on one column: midpoints of distinct values, plus 'off'."""
    u = np.unique(values[np.isfinite(values)])
    off = -math.inf if direction == "min" else math.inf
    if len(u) == 0:
        return np.array([off])
    mids = (u[:-1] + u[1:]) / 2.0
    return np.concatenate([[off], mids])


def _pass(values: NDArray[np.float64], direction: str, t: float) -> NDArray[np.bool_]:
    with np.errstate(invalid="ignore"):
        if direction == "min":
            return np.asarray(values >= t, dtype=bool)
        return np.asarray(~(values > t), dtype=bool)  # NaN passes a max gate


def _ascend(
    cols: list[NDArray[np.float64]],
    dirs: list[str],
    fault: NDArray[np.bool_],
    thresholds: list[float],
    *,
    rounds: int = 4,
    only: int | None = None,
) -> tuple[list[float], float]:
    """Coordinate ascent of balanced accuracy over the thresholds (or only column ``only``)."""
    t = list(thresholds)

    def score(ok: NDArray[np.bool_]) -> float:
        return _bal_acc(~ok, fault)

    ok_all = np.ones(len(fault), dtype=bool)
    for j in range(len(cols)):
        ok_all &= _pass(cols[j], dirs[j], t[j])
    best = score(ok_all)
    order = range(len(cols)) if only is None else [only]
    for _ in range(rounds if only is None else 1):
        improved = False
        for i in order:
            others = np.ones(len(fault), dtype=bool)
            for j in range(len(cols)):
                if j != i:
                    others &= _pass(cols[j], dirs[j], t[j])
            cand = _candidates(cols[i], dirs[i])
            ok = others[None, :] & np.stack([_pass(cols[i], dirs[i], v) for v in cand])
            bal = 0.5 * ((~ok)[:, fault].mean(axis=1) + ok[:, ~fault].mean(axis=1))
            top = float(bal.max())
            tied = np.flatnonzero(bal >= top - 1e-12)
            # the loosest of the equally good thresholds: 'off', else the most permissive
            k = 0 if tied[0] == 0 else int(tied[-1]) if dirs[i] == "max" else int(tied[0])
            if top > best + 1e-12:
                improved = True
            if top >= best - 1e-12:
                best, t[i] = max(best, top), float(cand[k])
        if not improved:
            break
    return t, best


def _grid_search(
    cols: list[NDArray[np.float64]], dirs: list[str], fault: NDArray[np.bool_], grid: int
) -> list[float]:
    """The best thresholds of a coarse grid over the first four columns (the fifth off)."""
    offs = [(-math.inf if d == "min" else math.inf) for d in dirs]

    # coarse grid over the first four columns
    def grid_values(v: NDArray[np.float64], d: str) -> NDArray[np.float64]:
        f = v[np.isfinite(v)]
        off = -math.inf if d == "min" else math.inf
        if len(f) == 0:
            return np.array([off])
        return np.concatenate([[off], np.unique(np.quantile(f, np.linspace(0.05, 0.95, grid)))])

    g = [grid_values(cols[i], dirs[i]) for i in range(4)]
    passes = [np.stack([_pass(cols[i], dirs[i], t) for t in g[i]]) for i in range(4)]
    best_t = list(offs)
    best = _bal_acc(np.zeros(len(fault), dtype=bool), fault)
    for a in range(len(g[0])):
        pa = passes[0][a]
        for b in range(len(g[1])):
            pab = pa & passes[1][b]
            for c in range(len(g[2])):
                pabc = pab & passes[2][c]
                ok = pabc[None, :] & passes[3]  # (len(g3), N)
                rej = ~ok
                tpr = rej[:, fault].mean(axis=1)
                tnr = ok[:, ~fault].mean(axis=1)
                bal = 0.5 * (tpr + tnr)
                d = int(np.argmax(bal))
                if bal[d] > best + 1e-12:
                    best = float(bal[d])
                    best_t = [g[0][a], g[1][b], g[2][c], g[3][d], math.inf]
    return best_t


def fit_classical(
    records_or_table: Sequence[Any] | Mapping[str, ArrayLike],
    *,
    grid: int = 12,
    rounds: int = 4,
) -> ClassicalClosureTest:
    """The classical test with thresholds maximising balanced accuracy on training candidates.

    A coarse grid (``grid`` quantiles per column, plus "off") over response, std xy, std theta
    and translation disagreement, then coordinate ascent over every threshold (all distinct
    midpoints, the rotation disagreement too) until no threshold improves, started from the
    grid's best, from every gate off and from each gate alone at its best; the best result
    wins. Among equally good thresholds of a column the loosest is kept.

    Args:
        records_or_table: `ClosureRecord` list, or a table with `CLASSICAL_FEATURES` and
            ``label`` columns. Ambiguous (-1) rows are ignored.
        grid: Quantiles per column of the coarse grid.
        rounds: Maximum coordinate-ascent rounds.

    Raises:
        ModelError: No normal or no fault candidate.
    """
    table = _as_table(records_or_table, CLASSICAL_FEATURES, icp=False)
    y = np.asarray(table["label"]).astype(np.int64)
    keep = y >= 0
    fault = y[keep] == 1
    if not (fault.any() and (~fault).any()):
        raise ModelError(
            f"fit_classical: needs normal and fault candidates; got {int((~fault).sum())} normal "
            f"and {int(fault.sum())} fault"
        )
    cols = [np.asarray(table[c], dtype=np.float64)[keep] for c, _ in _CLASSICAL_DIRS]
    dirs = [d for _, d in _CLASSICAL_DIRS]
    offs = [(-math.inf if d == "min" else math.inf) for d in dirs]

    best_t = _grid_search(cols, dirs, fault, grid)

    # coordinate ascent with exact thresholds, from the grid's best, from every gate off and
    # from each single gate at its best (a local optimum of one start is not final)
    starts = [best_t, list(offs)]
    for i in range(len(cols)):
        single = list(offs)
        single[i] = _ascend(cols, dirs, fault, list(offs), only=i)[0][i]
        starts.append(single)
    results = [_ascend(cols, dirs, fault, list(t0), rounds=rounds) for t0 in starts]
    best_t, best = max(results, key=lambda r: r[1])
    test = ClassicalClosureTest(*best_t)
    logger.info("fitted classical closure test: %r (balanced accuracy %.3f)", test, best)
    return test


def _as_table(
    records_or_table: Sequence[Any] | Mapping[str, ArrayLike],
    features: Sequence[str],
    *,
    icp: bool = True,
) -> dict[str, NDArray[Any]]:
    if isinstance(records_or_table, Mapping):
        missing = [f for f in (*features, "label") if f not in records_or_table]
        if missing:
            raise ModelError(f"candidate table: missing column(s) {missing}")
        return {k: np.asarray(v) for k, v in records_or_table.items()}
    if icp:
        return dict(candidate_table(list(records_or_table)))
    rows: dict[str, list[float]] = {k: [] for k in (*features, "label")}
    for rec in records_or_table:
        cand = rec.candidate
        s = cand.std
        dm, dr = cand.disagreement
        vals = {
            "response": cand.score,
            "coarse_response": cand.coarse_score,
            "std_xy": max(float(s[0]), float(s[1])),
            "std_theta": float(s[2]),
            "disagreement_m": dm,
            "disagreement_rad": dr,
            "label": float(rec.label),
        }
        for k in rows:
            rows[k].append(float(vals[k]))
    return {k: np.asarray(v, dtype=np.float64) for k, v in rows.items()}


def _validate_kind(
    kind: Kind,
    data: Mapping[str, NDArray[np.float64]],
    y: NDArray[np.int64],
    g: NDArray[Any],
    features: Sequence[str],
) -> tuple[float, float, float]:
    """Out-of-fold (leave one group out) balanced accuracy, ROC AUC and threshold of a kind."""
    from sklearn.metrics import roc_auc_score

    uniq = np.unique(g)
    oof = np.full(len(y), np.nan)
    for grp in uniq:
        test = g == grp
        train_y = y[~test]
        if not ((train_y == 0).any() and (train_y == 1).any()):
            continue
        m = MetricsModelDetector(list(features), kind=kind, name=f"closure-{kind}")
        m.fit({f: v[~test] for f, v in data.items()}, train_y)
        oof[test] = m.predict_proba({f: v[test] for f, v in data.items()})
    have = np.isfinite(oof)
    t = choose_threshold(y[have], oof[have])
    bal = balanced_accuracy(y[have], oof[have], t)
    auc = float(roc_auc_score(y[have], oof[have])) if len(np.unique(y[have])) == 2 else float("nan")
    logger.info("closure judge %s: out-of-fold balanced accuracy %.3f, AUC %.3f", kind, bal, auc)
    return bal, auc, t


def fit_learned_judge(
    table: Mapping[str, ArrayLike],
    groups: ArrayLike,
    *,
    kinds: Sequence[Kind] = ("gbm", "logistic"),
    features: Sequence[str] = LEARNED_FEATURES,
) -> LearnedClosureJudge:
    """Fit on a labelled table; threshold and kind chosen on out-of-fold predictions.

    Each group (a sequence: scenario and seed) is predicted by a model fitted without it;
    the kind with the best out-of-fold balanced accuracy at its `choose_threshold`
    threshold (ties: higher ROC AUC) wins, and the final model of that kind is fitted on
    every row. Ambiguous rows are dropped.

    Args:
        table: Feature columns and ``label``.
        groups: Group id per row (rows of one group are never split).
        kinds: Model kinds to try.
        features: Columns to read.

    Raises:
        ModelError: Fewer than two groups, or a class missing.
    """
    y_all = np.asarray(table["label"]).astype(np.int64)
    g_all = np.asarray(groups)
    keep = y_all >= 0
    data = {f: np.asarray(table[f], dtype=np.float64)[keep] for f in features}
    y, g = y_all[keep], g_all[keep]
    if not ((y == 0).any() and (y == 1).any()):
        raise ModelError("fit_learned_judge: needs normal and fault candidates")
    uniq = np.unique(g)
    if len(uniq) < 2:
        raise ModelError("fit_learned_judge: needs at least two groups to validate")
    scores: dict[Kind, tuple[float, float, float]] = {}
    for kind in kinds:
        scores[kind] = _validate_kind(kind, data, y, g, features)
    best = max(scores, key=lambda k: (scores[k][0], scores[k][1]))
    t = scores[best][2]
    model = MetricsModelDetector(list(features), kind=best, name=f"closure-{best}")
    model.fit(data, y)
    model.threshold = t
    prov = {
        "kind": best,
        "threshold_rule": THRESHOLD_RULE,
        "validation": {
            k: {"balanced_accuracy": v[0], "roc_auc": v[1], "threshold": v[2]}
            for k, v in scores.items()
        },
        "n_train": len(y),
        "n_normal": int((y == 0).sum()),
        "n_fault": int((y == 1).sum()),
        "n_ambiguous_dropped": int((~keep).sum()),
        "groups": [str(x) for x in uniq],
    }
    return LearnedClosureJudge(model, float(t), prov)


__all__ = [
    "CLASSICAL_RULE",
    "THRESHOLD_RULE",
    "Kind",
    "fit_classical",
    "fit_learned_judge",
]
