"""Evaluation of fault detectors: paper Table 2 columns, ROC curves, confusion matrices.

Fault is the **positive** class throughout: TP = a fault flagged as fault, FN = a fault that
was missed, FP = a normal match flagged as fault, TN = a normal match passed. Recall is the
fraction of faults caught, precision the fraction of flags that were faults.

Ambiguous pairs (label -1) have no right answer; they are reported separately as a count and
the fraction each method flags.

Balanced accuracy is the mean of the fault recall and the normal recall (robust to the class
ratio of an environment); ECE is the expected calibration error of a method whose scores are
probabilities (`scanguard.scoring.expected_calibration_error`: 15 equal-width bins,
weighted by count; NaN for the threshold baselines, whose scores are monotone ranks, not
probabilities). The reliability diagram of each probabilistic method is ``reliability.png``.

`evaluate_store` evaluates the CNN and the classical baselines (fitted on the store's
training split, thresholds chosen on its validation split by the CNN's rule, `fit_baselines`)
on chosen splits, per environment and overall, and writes ``results.json``, ``results.csv``,
ROC curves (paper Figure 18) and confusion matrices as PNG. The model card's held-out figures,
where every method's threshold comes from the same held-out selection pairs, are
`scanguard.detect.protocol` (``benchmarks/model_card.py``).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.dataset.store import PairStore
from scanguard.detect.baselines.metrics_model import MetricsModelDetector
from scanguard.detect.baselines.registry import BASELINES, ODOMETRY_BASELINES, make_baseline
from scanguard.detect.calibrate import plot_reliability
from scanguard.detect.detector import FaultDetector
from scanguard.detect.features import store_features
from scanguard.detect.images import render_all
from scanguard.errors import ConfigError, ModelError
from scanguard.fsutil import atomic_write_text, save_figure
from scanguard.scoring import confusion, expected_calibration_error, roc_auc

log = logging.getLogger(__name__)

#: Columns of the result table, in print order.
COLUMNS: tuple[str, ...] = (
    "method",
    "environment",
    "n",
    "TP",
    "FN",
    "FP",
    "TN",
    "recall",
    "precision",
    "accuracy",
    "balanced_accuracy",
    "f1",
    "ece",
    "auc",
    "threshold",
    "n_ambiguous",
    "ambiguous_flagged",
)

ALL = "all"


@dataclass
class MethodScores:
    """Scores of one method on a set of pairs.

    Attributes:
        name: Method name (``cnn``, a baseline name, ...).
        scores: Fault score per pair (higher = fault).
        threshold: Operating threshold (flag when ``score >= threshold``).
        probabilistic: The scores are probabilities (ECE and reliability are reported).
    """

    name: str
    scores: NDArray[np.float64]
    threshold: float
    probabilistic: bool = True


@dataclass
class EvaluationResult:
    """Rows of the result table plus what is needed to plot it.

    Attributes:
        rows: One dict per (method, environment) with the `COLUMNS`.
        labels: Labels of the evaluated pairs.
        environment: Environment per pair.
        methods: Scores per method.
        meta: Free-form description (model, data, splits).
    """

    rows: list[dict[str, Any]]
    labels: NDArray[np.int64]
    environment: NDArray[np.str_]
    methods: list[MethodScores]
    meta: dict[str, Any] = field(default_factory=dict)

    def row(self, method: str, environment: str = ALL) -> dict[str, Any]:
        """The row of ``method`` in ``environment``."""
        for r in self.rows:
            if r["method"] == method and r["environment"] == environment:
                return r
        raise KeyError(f"no row for method {method!r} in environment {environment!r}")

    def to_json(self) -> str:
        """Results as JSON (NaN written as null)."""

        def clean(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return None
            return v

        rows = [{k: clean(v) for k, v in r.items()} for r in self.rows]
        return json.dumps(
            {"positive_class": "fault", "meta": self.meta, "rows": rows}, indent=2, default=str
        )

    def to_csv(self) -> str:
        """Results as CSV with the `COLUMNS` header."""
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(COLUMNS), extrasaction="ignore")
        w.writeheader()
        for r in self.rows:
            w.writerow(r)
        return buf.getvalue()


def table_rows(
    labels: ArrayLike,
    environment: ArrayLike,
    methods: Sequence[MethodScores],
    environments_order: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Per-environment and overall rows for every method (ambiguous pairs counted apart)."""
    y = np.asarray(labels).astype(np.int64)
    env = np.asarray(environment).astype(str)
    envs = list(environments_order) if environments_order else list(dict.fromkeys(env.tolist()))
    rows: list[dict[str, Any]] = []
    for m in methods:
        s = np.asarray(m.scores, dtype=np.float64)
        for e in [*envs, ALL]:
            sel = np.ones(len(y), bool) if e == ALL else env == e
            amb = sel & (y == -1)
            n_amb = int(amb.sum())
            row: dict[str, Any] = {"method": m.name, "environment": e}
            row.update(confusion(y[sel], s[sel], m.threshold))
            row["ece"] = expected_calibration_error(y[sel], s[sel]) if m.probabilistic else math.nan
            row["n_ambiguous"] = n_amb
            row["ambiguous_flagged"] = float(np.mean(s[amb] >= m.threshold)) if n_amb else math.nan
            rows.append(row)
    return rows


def plot_roc(result: EvaluationResult, path: str | Path) -> Path:
    """ROC curves, one panel per environment (paper Figure 18), all methods overlaid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.metrics import roc_curve

    envs = [*dict.fromkeys(result.environment.tolist()), ALL]
    ncol = min(3, len(envs))
    nrow = math.ceil(len(envs) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 4 * nrow), squeeze=False)
    y = result.labels
    for k, e in enumerate(envs):
        ax = axes[k // ncol][k % ncol]
        sel = ((y == 0) | (y == 1)) & (
            np.ones(len(y), bool) if e == ALL else result.environment == e
        )
        for m in result.methods:
            yy = y[sel]
            if len(np.unique(yy)) < 2:
                continue
            fpr, tpr, _ = roc_curve(yy, m.scores[sel])
            auc = roc_auc(yy, m.scores[sel])
            ax.plot(fpr, tpr, lw=1.5 if m.name == "cnn" else 1.0, label=f"{m.name} ({auc:.3f})")
        ax.plot([0, 1], [0, 1], "k:", lw=0.8)
        ax.set_title(e)
        ax.set_xlabel("false positive rate")
        ax.set_ylabel("true positive rate (fault)")
        ax.legend(fontsize=7, loc="lower right")
        ax.grid(alpha=0.3)
    for k in range(len(envs), nrow * ncol):
        axes[k // ncol][k % ncol].axis("off")
    p = save_figure(fig, Path(path), dpi=100)
    return p


def plot_confusion(result: EvaluationResult, path: str | Path, method: str = "cnn") -> Path:
    """Confusion matrices of one method, one panel per environment (rows: true class)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in result.rows if r["method"] == method]
    ncol = min(3, len(rows))
    nrow = math.ceil(len(rows) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 3.4 * nrow), squeeze=False)
    for k, r in enumerate(rows):
        ax = axes[k // ncol][k % ncol]
        mat = np.array([[r["TP"], r["FN"]], [r["FP"], r["TN"]]])
        ax.imshow(mat, cmap="Blues")
        for i in range(2):
            for j in range(2):
                ax.text(j, i, str(mat[i, j]), ha="center", va="center", fontsize=12)
        ax.set_xticks([0, 1], ["fault", "normal"])
        ax.set_yticks([0, 1], ["fault", "normal"])
        ax.set_xlabel("predicted")
        ax.set_ylabel("true")
        ax.set_title(f"{r['environment']} (acc {r['accuracy']:.3f})", fontsize=9)
    for k in range(len(rows), nrow * ncol):
        axes[k // ncol][k % ncol].axis("off")
    fig.suptitle(method)
    p = save_figure(fig, Path(path), dpi=100)
    return p


def plot_reliability_result(
    result: EvaluationResult, path: str | Path, method: str = "cnn"
) -> Path:
    """Reliability diagrams of one method, one panel per environment plus ``all``."""
    m = next((x for x in result.methods if x.name == method), None)
    if m is None:
        raise ConfigError(f"no method {method!r} in the result")
    envs = [*dict.fromkeys(result.environment.tolist()), ALL]
    panels = []
    for e in envs:
        sel = np.ones(len(result.labels), bool) if e == ALL else result.environment == e
        panels.append((e, result.labels[sel], m.scores[sel]))
    return plot_reliability(panels, path, title=f"{method}: reliability")


def write_results(result: EvaluationResult, out_dir: str | Path) -> dict[str, Path]:
    """Write the result table, ROC curves, confusion matrices and reliability diagrams.

    Files: ``results.json``, ``results.csv``, ``roc.png``, ``confusion_<method>.png``, and
    ``reliability.png`` (the CNN's; ``reliability_<method>.png`` for the other probabilistic
    methods).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "results.json", "csv": out / "results.csv"}
    atomic_write_text(paths["json"], result.to_json())
    atomic_write_text(paths["csv"], result.to_csv())
    paths["roc"] = plot_roc(result, out / "roc.png")
    for m in result.methods:
        paths[f"confusion_{m.name}"] = plot_confusion(
            result, out / f"confusion_{m.name}.png", m.name
        )
        if m.probabilistic:
            name = "reliability" if m.name == "cnn" else f"reliability_{m.name}"
            paths[name] = plot_reliability_result(result, out / f"{name}.png", m.name)
    return paths


def evaluate_scores(
    labels: ArrayLike,
    environment: ArrayLike,
    methods: Sequence[MethodScores],
    meta: Mapping[str, Any] | None = None,
) -> EvaluationResult:
    """Build the result table from precomputed scores."""
    y = np.asarray(labels).astype(np.int64)
    env = np.asarray(environment).astype(str)
    for m in methods:
        if len(m.scores) != len(y):
            raise ConfigError(f"method {m.name!r}: {len(m.scores)} scores for {len(y)} pairs")
    return EvaluationResult(
        rows=table_rows(y, env, methods),
        labels=y,
        environment=env,
        methods=list(methods),
        meta=dict(meta or {}),
    )


def fit_baselines(
    store: Any,
    names: Sequence[str],
    splits: Sequence[str] = ("train",),
    select_splits: Sequence[str] | None = ("val",),
    *,
    skip_unfittable: bool = False,
) -> dict[str, Any]:
    """Fit classical baselines on a pair store's training split (never on test data).

    The one place baselines are fitted (`evaluate_store` and `scanguard.apps.run_baseline` both call
    it, so they compare the CNN against the same detectors). Each detector is fitted on the
    ``splits`` pairs and its operating threshold is chosen on the ``select_splits`` pairs by the
    CNN's rule (`scanguard.detect.baselines.base.THRESHOLD_RULE`: maximum balanced accuracy on pairs
    the detector was not fitted on). When the store has no labelled pairs of both classes in
    ``select_splits`` (or it is None / empty) the thresholds are chosen on the fitting pairs,
    with a warning.

    Args:
        store: A `scanguard.dataset.PairStore` (or what `PairStore.open` accepts).
        names: Baseline names from `scanguard.detect.baselines.registry.BASELINES`.
        splits: Splits used for fitting.
        select_splits: Splits the thresholds are chosen on (default: the validation split).
        skip_unfittable: Leave out (with a warning) a baseline that cannot be fitted on this
            store (a feature it lacks) instead of raising.

    Returns:
        Fitted detectors by name (each with ``select_score``: its balanced accuracy, or
        accuracy, on the selection pairs).

    Raises:
        ConfigError: The store has no labelled pairs in ``splits``.
        ModelError: A baseline cannot be fitted (unless ``skip_unfittable``).
    """
    ps = store if isinstance(store, PairStore) else PairStore.open(store)
    idx = ps.indices(list(splits))
    if len(idx) == 0:
        where = str(store) if isinstance(store, str | Path) else _describe_store(ps)
        raise ConfigError(
            f"{where}: no labelled pairs in split(s) {list(splits)} to fit the baselines on "
            "(a store of recordings holds only 'heldout'); fit them on a store with a train "
            "split (--baseline-data DIR) or skip them (--baselines none)"
        )
    all_labels = np.asarray(ps.records["label"])
    feats = store_features(ps, idx)
    labels = all_labels[idx]
    sel = ps.indices(list(select_splits)) if select_splits else idx[:0]
    if (all_labels[sel] == 0).any() and (all_labels[sel] == 1).any():
        select = (store_features(ps, sel), all_labels[sel])
        where_sel = f"{len(sel)} {'+'.join(select_splits or ())} pairs"
    else:
        log.warning(
            "no labelled pairs of both classes in split(s) %s: choosing the baseline "
            "thresholds on the %d fitting pairs",
            list(select_splits or ()),
            len(idx),
        )
        select = (feats, labels)
        where_sel = "the fitting pairs"
    out = {}
    for name in names:
        try:
            out[name] = make_baseline(name).fit(feats, labels, select=select)
        except (ModelError, ValueError) as exc:  # a feature this store lacks, too few pairs
            if not skip_unfittable:
                raise
            log.warning("baseline %s cannot be fitted: %s", name, exc)
            continue
        log.info(
            "fitted baseline %s on %d %s pairs, threshold %.6g chosen on %s",
            name,
            len(idx),
            "+".join(splits),
            out[name].threshold,
            where_sel,
        )
    return out


def _describe_store(store: Any) -> str:
    files = [str(f) for f in getattr(store, "files", [])]
    if not files:
        return "the store"
    return files[0] if len(files) == 1 else f"{files[0]} (+{len(files) - 1} more files)"


def fail_safe_scores(
    method: str, scores: ArrayLike, threshold: float
) -> tuple[NDArray[np.float64], int]:
    """Scores with every non-finite value replaced by a sure fault (as the guard treats it).

    A NaN or infinite fault score has no ranking; the online guard rejects such a match
    (`scanguard.slam.stream.ScanGuard`), so evaluation counts it as flagged: it is replaced by
    ``max(1, threshold, every finite score)``.

    Args:
        method: Method name (for the warning).
        scores: Fault scores.
        threshold: The method's operating threshold.

    Returns:
        The cleaned scores and how many were replaced.
    """
    s = np.asarray(scores, dtype=np.float64).copy()
    bad = ~np.isfinite(s)
    n_bad = int(bad.sum())
    if n_bad:
        finite = s[~bad]
        top = max(1.0, float(threshold), float(finite.max()) if finite.size else 1.0)
        s[bad] = top
        log.warning(
            "%s: %d of %d fault scores are not finite; counted as flagged faults",
            method,
            n_bad,
            s.size,
        )
    return s, n_bad


def evaluate_store(
    model: Any,
    store: Any,
    out_dir: str | Path | None = None,
    *,
    splits: Sequence[str] | None = ("test", "heldout"),
    environments: Sequence[str] | None = None,
    baselines: Sequence[str] | None = None,
    baseline_store: Any = None,
    baseline_splits: Sequence[str] = ("train",),
    baseline_select_splits: Sequence[str] | None = ("val",),
    backend: str = "torch",
) -> EvaluationResult:
    """Evaluate the CNN and the classical baselines on a pair store.

    Args:
        model: A `scanguard.detect.detector.FaultDetector`, a checkpoint path, or ``None`` for the
            shipped model.
        store: Pair store (build folder, ``.h5`` file(s), or an open `PairStore`).
        out_dir: Where to write JSON/CSV/PNG results (``None``: nothing is written).
        splits: Splits to evaluate (``None``: all pairs).
        environments: Restrict to these environments.
        baselines: Baseline names (``None``: all of `scanguard.detect.baselines.registry.BASELINES`,
            plus `ODOMETRY_BASELINES` when some evaluated pair has odometry;
            empty: none).
        baseline_store: Store whose ``baseline_splits`` the baselines are fitted on (default:
            ``store``) — e.g. the simulated training data when evaluating a real recording.
        baseline_splits: Training split(s) for the baselines.
        baseline_select_splits: Split(s) of the baseline store their thresholds are chosen on
            (`fit_baselines`: the CNN's threshold rule; the training split when empty).
        backend: ``"torch"`` or ``"onnx"``.

    Returns:
        The result table (rows per method and environment, plus ``all``).

    Non-finite scores (a model that outputs NaN) are counted as flagged faults, as the guard
    treats them (`fail_safe_scores`), and their number per method is in
    ``meta["non_finite_scores"]``.

    Raises:
        ConfigError: Nothing to evaluate, or no training pairs to fit the baselines on.
        ModelError: The model's fault probability is not finite for any pair.
    """
    det = model if isinstance(model, FaultDetector) else FaultDetector.load(model, backend=backend)  # type: ignore[arg-type]
    ps = store if isinstance(store, PairStore) else PairStore.open(store)
    idx = ps.indices(
        None if splits is None else list(splits),
        environment=None if environments is None else list(environments),
        include_ambiguous=True,
    )
    if len(idx) == 0:
        raise ConfigError(
            f"nothing to evaluate: no pairs in split(s) {splits} / environment(s) {environments}"
        )
    rec = ps.records
    labels = np.asarray(rec["label"], dtype=np.int64)[idx]
    env = np.asarray(rec["environment"]).astype(str)[idx]
    names = _baseline_names(baselines, rec, idx)
    # fit the baselines first: a store they cannot be fitted on fails before the slow part
    base = ps if baseline_store is None else baseline_store
    fitted = fit_baselines(base, names, baseline_splits, baseline_select_splits) if names else {}
    images = render_all(ps, idx, det.style, progress=True)
    feats = store_features(ps, idx, det.odometry_noise, det.reads_profile)
    raw = det.predict_images(images, features=feats if det.metric_names else None)
    if len(raw) and not np.isfinite(raw).any():
        raise ModelError(
            f"{det.source}: the model's fault probability is not finite for any of the "
            f"{len(raw)} pairs (a diverged or corrupt model)"
        )
    methods, baseline_info, non_finite = _score_methods(det, raw, fitted, feats)
    meta = _meta(det, ps, splits, baseline_info, non_finite)
    result = evaluate_scores(labels, env, methods, meta)
    if out_dir is not None:
        write_results(result, out_dir)
    return result


def _meta(
    det: FaultDetector,
    ps: PairStore,
    splits: Sequence[str] | None,
    baseline_info: dict[str, Any],
    non_finite: dict[str, int],
) -> dict[str, Any]:
    """The ``meta`` block of an evaluation result."""
    return {
        "model": det.source,
        "style": det.style.model_dump(mode="json"),
        "store": [str(f) for f in ps.files][:3] + (["..."] if len(ps.files) > 3 else []),
        "splits": None if splits is None else list(splits),
        "baselines": baseline_info,
        "label_thresholds": det.label_thresholds,
        "non_finite_scores": {k: v for k, v in non_finite.items() if v},
    }


def _baseline_names(
    baselines: Sequence[str] | None, rec: Mapping[str, Any], idx: NDArray[np.int64]
) -> list[str]:
    """The baselines to evaluate: the given ones, or the defaults (plus the odometry ones)."""
    names = list(BASELINES) if baselines is None else list(baselines)
    odo = rec.get("odometry_increment")
    if (
        baselines is None
        and odo is not None
        and np.isfinite(np.asarray(odo)[idx]).all(axis=1).any()
    ):
        # pairs with odometry: a careful user would also test the odometry disagreement
        names += list(ODOMETRY_BASELINES)
    return names


def _score_methods(
    det: FaultDetector,
    raw: NDArray[np.float64],
    fitted: Mapping[str, Any],
    feats: Mapping[str, NDArray[np.float64]],
) -> tuple[list[MethodScores], dict[str, Any], dict[str, int]]:
    """Fail-safe scores of the CNN and every fitted baseline.

    Returns:
        The method scores, the baselines' descriptions and the non-finite count per method.
    """
    non_finite: dict[str, int] = {}
    cnn_scores, non_finite["cnn"] = fail_safe_scores("cnn", raw, det.threshold)
    methods = [MethodScores("cnn", cnn_scores, det.threshold)]
    baseline_info: dict[str, Any] = {}
    for name, b in fitted.items():
        # ThresholdDetector flags strictly above its threshold, where its score is 0.5
        t = b.threshold if isinstance(b, MetricsModelDetector) else float(np.nextafter(0.5, 1))
        scores, non_finite[name] = fail_safe_scores(name, b.predict_proba(feats), t)
        probabilistic = isinstance(b, MetricsModelDetector)
        methods.append(MethodScores(name, scores, t, probabilistic))
        baseline_info[name] = {
            "threshold": float(b.threshold),
            "select_score": getattr(b, "select_score", None),
            "n_select": getattr(b, "n_select", None),
            **_describe(b),
        }
    return methods, baseline_info, non_finite


def _describe(detector: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"type": type(detector).__name__}
    for attr in ("feature", "direction", "kind"):
        if hasattr(detector, attr):
            out[attr] = getattr(detector, attr)
    return out


def best_baseline(result: EvaluationResult, environment: str = ALL) -> str | None:
    """Name of the baseline with the highest accuracy in ``environment`` (None if none)."""
    rows = [
        r
        for r in result.rows
        if r["environment"] == environment and r["method"] != "cnn" and math.isfinite(r["accuracy"])
    ]
    return max(rows, key=lambda r: r["accuracy"])["method"] if rows else None
