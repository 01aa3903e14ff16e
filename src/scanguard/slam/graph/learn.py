"""The learned loop-closure judge, and the classical closure test fitted on the same data.

`LearnedClosureJudge` (``learned``) is a small classifier (the detector issue's shared
`scanguard.detect.baselines.metrics_model.MetricsModelDetector`: gradient boosting or logistic
regression)
over scale-free features of a candidate (`LEARNED_FEATURES`, computed by
`scanguard.slam.graph.harvest.candidate_features`): the loop matcher's responses and
response-surface standard deviations, how far the closure would move the graph (absolute and
per metre of path since the target node), and the ``icp-paper`` quality metrics of the pair
from the proposed pose. It rejects a candidate when its fault probability reaches the
threshold.

The threshold follows the project's rule (`scanguard.scoring.choose_threshold`: max
balanced accuracy) on **validation** probabilities: out-of-fold predictions with the training
groups (sequences) left out one at a time, never the data the final model is fitted on and
never the test data. The model kind (``gbm`` or ``logistic``) is chosen on the same
out-of-fold predictions.

`fit_classical` fits the classical test a careful user would configure: Karto's minimum
response and maximum standard deviations plus a maximum-disagreement gate (how far the
closure moves the graph), by a grid search and coordinate ascent maximising the balanced
accuracy on the training candidates (`ClassicalClosureTest`).

`save_closure_judge` / `load_closure_judge` write / read both in one JSON file with their
training provenance; the package ships one in ``scanguard/models/closure_judge.json``
(`default_judge_path`), which `scanguard.slam.graph.closure.judge_for_gate` uses. The sklearn
model is pickled (base64) inside the JSON: load only files you trust.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.detect.baselines.metrics_model import MetricsModelDetector
from scanguard.errors import ModelError
from scanguard.fsutil import atomic_write_text
from scanguard.scoring import balanced_accuracy, choose_threshold
from scanguard.slam.graph.closure import ClosureCandidate, ClosureVerdict, ResponseTest
from scanguard.slam.graph.harvest import candidate_features

logger = logging.getLogger(__name__)

JUDGE_FILE_NAME = "closure_judge.json"
JUDGE_FORMAT = "scanguard-closure-judge"
JUDGE_VERSION = 1
THRESHOLD_RULE = (
    "scanguard.scoring.choose_threshold (max balanced accuracy) on out-of-fold "
    "validation probabilities (leave-one-sequence-out over the training sequences)"
)
CLASSICAL_RULE = (
    "grid search + coordinate ascent maximising balanced accuracy on the training candidates"
)

LEARNED_FEATURES: tuple[str, ...] = (
    "response",
    "coarse_response",
    "std_xy",
    "std_theta",
    "disagreement_m",
    "disagreement_rad",
    "disagreement_m_per_m",
    "disagreement_rad_per_m",
    "path_gap",
    "icp_mean_residual",
    "icp_median_residual",
    "icp_inlier_ratio",
    "icp_eig_min_per_inlier",
    "icp_condition_number",
    "icp_converged",
    "icp_shift_m",
    "icp_shift_rad",
)
"""Features of the learned judge (no beam counts: they depend on the sensor)."""

CLASSICAL_FEATURES: tuple[str, ...] = (
    "response",
    "std_xy",
    "std_theta",
    "disagreement_m",
    "disagreement_rad",
)
"""Columns the classical test reads."""

Kind = Literal["gbm", "logistic"]


def default_judge_path() -> Path:
    """Path of the closure-judge file shipped with the package (it may not exist)."""
    return Path(str(resources.files("scanguard") / "models" / JUDGE_FILE_NAME))


# --------------------------------------------------------------------------------------------
# classical test
# --------------------------------------------------------------------------------------------


class ClassicalClosureTest(ResponseTest):
    """Karto's response test plus a disagreement gate (``classical``).

    A candidate passes when its fine response is at least ``min_response``, its standard
    deviations are at most ``max_std_xy`` (x and y) and ``max_std_theta``, and it would move
    the graph by at most ``max_disagreement_m`` and ``max_disagreement_rad`` (infinite = no
    gate; a candidate without a prior pose passes the gate).

    Args:
        min_response: Minimum fine response.
        max_std_xy: Maximum standard deviation in x and in y (m).
        max_std_theta: Maximum standard deviation in heading (rad).
        max_disagreement_m: Maximum translation between proposed and prior relative pose (m).
        max_disagreement_rad: Maximum rotation between them (rad).
    """

    name = "classical"

    def __init__(
        self,
        min_response: float,
        max_std_xy: float,
        max_std_theta: float,
        max_disagreement_m: float = math.inf,
        max_disagreement_rad: float = math.inf,
    ) -> None:
        super().__init__(min_response, max_std_xy, max_std_theta)
        self.max_disagreement_m = float(max_disagreement_m)
        self.max_disagreement_rad = float(max_disagreement_rad)

    def thresholds(self) -> dict[str, float]:
        """The thresholds by name (JSON: infinities as None)."""
        return {
            "min_response": self.min_response,
            "max_std_xy": self.max_std_xy,
            "max_std_theta": self.max_std_theta,
            "max_disagreement_m": self.max_disagreement_m,
            "max_disagreement_rad": self.max_disagreement_rad,
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible thresholds (infinite = None)."""
        return {k: (v if math.isfinite(v) else None) for k, v in self.thresholds().items()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ClassicalClosureTest:
        """Rebuild from `to_dict` output."""

        def get(key: str, default: float) -> float:
            v = data.get(key, default)
            return default if v is None else float(v)

        return cls(
            get("min_response", -math.inf),
            get("max_std_xy", math.inf),
            get("max_std_theta", math.inf),
            get("max_disagreement_m", math.inf),
            get("max_disagreement_rad", math.inf),
        )

    def passes(self, table: Mapping[str, ArrayLike]) -> NDArray[np.bool_]:
        """Which rows of a feature table (`CLASSICAL_FEATURES` columns) pass the test."""
        col = {k: np.asarray(table[k], dtype=np.float64) for k in CLASSICAL_FEATURES}
        with np.errstate(invalid="ignore"):
            ok = col["response"] >= self.min_response
            ok &= col["std_xy"] <= self.max_std_xy
            ok &= col["std_theta"] <= self.max_std_theta
            dm, dr = col["disagreement_m"], col["disagreement_rad"]
            ok &= ~(dm > self.max_disagreement_m)  # NaN (no prior) passes the gate
            ok &= ~(dr > self.max_disagreement_rad)
        return np.asarray(ok, dtype=bool)

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """Accept when the response, the standard deviations and the disagreement pass."""
        s = candidate.std
        dm, dr = candidate.disagreement
        row = {
            "response": [candidate.score],
            "std_xy": [max(float(s[0]), float(s[1]))],
            "std_theta": [float(s[2])],
            "disagreement_m": [dm],
            "disagreement_rad": [dr],
        }
        return ClosureVerdict(bool(self.passes(row)[0]), candidate.score, self.name)

    def __repr__(self) -> str:
        t = ", ".join(f"{k}={v:.4g}" for k, v in self.thresholds().items())
        return f"ClassicalClosureTest({t})"


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


# --------------------------------------------------------------------------------------------
# learned judge
# --------------------------------------------------------------------------------------------


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
        from scanguard.slam.graph.harvest import candidate_table

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


@dataclass
class LearnedClosureJudge:
    """A classifier over candidate features; rejects when the fault probability >= threshold.

    Attributes:
        model: The fitted `MetricsModelDetector` (its ``features`` are the columns it reads).
        threshold: Fault-probability threshold.
        provenance: How it was trained (scenarios, seeds, counts, rule...).
    """

    model: MetricsModelDetector
    threshold: float
    provenance: dict[str, Any] = field(default_factory=dict)
    name: str = "learned"

    @property
    def features(self) -> list[str]:
        """Feature columns the model reads."""
        return list(self.model.features or ())

    def predict_proba(self, table: Mapping[str, ArrayLike]) -> NDArray[np.float64]:
        """Fault probability of each row of a feature table."""
        cols = {f: np.asarray(table[f], dtype=np.float64) for f in self.features}
        return self.model.predict_proba(cols)

    def probability(self, candidate: ClosureCandidate) -> float:
        """Fault probability of one candidate (NaN is returned as 1: a fault)."""
        feats = candidate_features(candidate)
        p = float(self.predict_proba({f: [feats[f]] for f in self.features})[0])
        return p if math.isfinite(p) else 1.0

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        """Accept when the fault probability is below the threshold."""
        p = self.probability(candidate)
        return ClosureVerdict(p < self.threshold, p, self.name)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state."""
        return {
            "threshold": self.threshold,
            "model": self.model.to_dict(),
            "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LearnedClosureJudge:
        """Rebuild from `to_dict` output."""
        model = MetricsModelDetector.from_dict(data["model"])
        if model.model is None:
            raise ValueError("the learned model is not fitted")
        threshold = float(data["threshold"])
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"threshold {threshold} outside (0, 1)")
        return cls(model, threshold, dict(data.get("provenance", {})))

    @classmethod
    def fit(
        cls,
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
        from sklearn.metrics import roc_auc_score

        y_all = np.asarray(table["label"]).astype(np.int64)
        g_all = np.asarray(groups)
        keep = y_all >= 0
        data = {f: np.asarray(table[f], dtype=np.float64)[keep] for f in features}
        y, g = y_all[keep], g_all[keep]
        if not ((y == 0).any() and (y == 1).any()):
            raise ModelError("LearnedClosureJudge.fit: needs normal and fault candidates")
        uniq = np.unique(g)
        if len(uniq) < 2:
            raise ModelError("LearnedClosureJudge.fit: needs at least two groups to validate")
        scores: dict[Kind, tuple[float, float, float]] = {}
        for kind in kinds:
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
            auc = (
                float(roc_auc_score(y[have], oof[have]))
                if len(np.unique(y[have])) == 2
                else float("nan")
            )
            scores[kind] = (bal, auc, t)
            logger.info(
                "closure judge %s: out-of-fold balanced accuracy %.3f, AUC %.3f", kind, bal, auc
            )
        best = max(scores, key=lambda k: (scores[k][0], scores[k][1]))
        bal, auc, t = scores[best]
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
        return cls(model, float(t), prov)


# --------------------------------------------------------------------------------------------
# file
# --------------------------------------------------------------------------------------------


@dataclass
class ClosureJudgeFile:
    """Contents of a closure-judge file.

    Attributes:
        learned: The learned judge.
        classical: The fitted classical test (None when the file has none).
        provenance: Training provenance (scenarios, seeds, counts, rules...).
        path: The file it was read from.
    """

    learned: LearnedClosureJudge
    classical: ClassicalClosureTest | None
    provenance: dict[str, Any]
    path: Path | None = None


def save_closure_judge(
    path: str | Path,
    learned: LearnedClosureJudge,
    classical: ClassicalClosureTest | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Write a closure-judge file (JSON) atomically."""
    p = Path(path)
    data = {
        "format": JUDGE_FORMAT,
        "version": JUDGE_VERSION,
        "learned": learned.to_dict(),
        "classical": None if classical is None else classical.to_dict(),
        "provenance": dict(provenance or {}),
    }
    atomic_write_text(p, json.dumps(data, indent=1, default=_json_default))
    return p


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def load_closure_judge(path: str | Path | None = None) -> ClosureJudgeFile:
    """Read a closure-judge file (None = the shipped one).

    Raises:
        ModelError: Missing, unreadable or corrupt; the one-line message names the file.
    """
    p = default_judge_path() if path is None else Path(path)
    if not p.is_file():
        raise ModelError(f"{p}: closure-judge file not found")
    try:
        data = json.loads(p.read_text())
        if not isinstance(data, dict) or data.get("format") != JUDGE_FORMAT:
            raise ValueError(f"format is not {JUDGE_FORMAT!r}")
        if int(data.get("version", 0)) > JUDGE_VERSION:
            raise ValueError(f"version {data.get('version')} is newer than {JUDGE_VERSION}")
        learned = LearnedClosureJudge.from_dict(data["learned"])
        block = data.get("classical")
        classical = None if block is None else ClassicalClosureTest.from_dict(block)
        prov = dict(data.get("provenance") or {})
    except Exception as exc:  # any failure to decode is a corrupt file
        problem = " ".join(str(exc).split()) or type(exc).__name__
        raise ModelError(f"{p}: not a valid closure-judge file ({problem})") from None
    return ClosureJudgeFile(learned, classical, prov, p)


__all__ = [
    "CLASSICAL_FEATURES",
    "JUDGE_FILE_NAME",
    "LEARNED_FEATURES",
    "ClassicalClosureTest",
    "ClosureJudgeFile",
    "LearnedClosureJudge",
    "default_judge_path",
    "fit_classical",
    "load_closure_judge",
    "save_closure_judge",
]
