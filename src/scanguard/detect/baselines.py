"""Classical scan-matching failure detectors, compared with the CNN in the same tables.

Every detector has the same small API (`Detector`): ``fit(features, labels, select=...)``
fits it on the training split and chooses its operating threshold on the selection set
``select`` (the validation split: pairs it was not fitted on), ``predict_proba(features)``
returns a score in ``[0, 1]`` where higher means "more likely a fault" (label 1),
``predict(features)`` returns 0/1, and ``threshold`` / ``name`` describe it. ``features`` is
either a mapping of named columns (the keys of `scanguard.matching.MatchResult.metrics` plus
``gmapping_score``) or a 2-D array.

The comparison with the CNN is meant to be fair, i.e. against what a careful user would
configure: every default detector reads only **scale-free** features (the same meaning for any
sensor and robot speed: `SCALE_FREE_METRICS_FEATURES`; raw counts, raw eigenvalues, the raw
GMapping score and the motion size are `SCALE_DEPENDENT_METRICS_FEATURES`), and every threshold
is chosen by the CNN's rule (`THRESHOLD_RULE`: maximum balanced accuracy on the selection set,
`scanguard.scoring.choose_threshold` for probabilities).

* `ThresholdDetector` — one quality metric and a direction (``"high"``: large values mean
  fault, e.g. the ICP residual; ``"low"``: small values mean fault, e.g. the inlier ratio, the
  smallest Hessian eigenvalue per inlier or the per-beam GMapping score). The threshold
  maximises the balanced accuracy (or the plain accuracy), so class imbalance does not push it
  to "everything is normal".
* `MetricsModelDetector` — gradient boosting (or logistic regression on standardised,
  log-compressed features) over the scale-free quality metrics together, its probability
  threshold chosen by `scanguard.scoring.choose_threshold`.
* `gmapping_score` — GMapping's ``ScanMatcher::score`` with the previous scan as the map.

`BASELINES` names the default set used in the evaluation table; `make_baseline` builds one,
`save_detector` / `load_detector` ship fitted ones (JSON; the sklearn model is pickled into the
JSON as base64, so only load files you trust).
"""

from __future__ import annotations

import base64
import json
import logging
import math
import pickle
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import ConfigError, ModelError
from scanguard.fsutil import atomic_write_text
from scanguard.pairs.odometry import ODOMETRY_FEATURES
from scanguard.scoring import balanced_accuracy

log = logging.getLogger(__name__)

__all__ = [
    "BASELINES",
    "DEFAULT_METRICS_FEATURES",
    "LEGACY_METRICS_FEATURES",
    "ODOMETRY_BASELINES",
    "SCALE_DEPENDENT_METRICS_FEATURES",
    "SCALE_FREE_METRICS_FEATURES",
    "THRESHOLD_RULE",
    "Detector",
    "FeaturesLike",
    "MetricsModelDetector",
    "ThresholdDetector",
    "load_detector",
    "make_baseline",
    "save_detector",
    "with_derived_features",
]

FeaturesLike = Mapping[str, ArrayLike] | ArrayLike
"""Named feature columns ``{name: (N,)}`` or an ``(N, K)`` array (``(N,)`` for one feature)."""

FloatArray = NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------------

SCALE_FREE_METRICS_FEATURES: tuple[str, ...] = (
    "mean_residual",
    "median_residual",
    "inlier_ratio",
    "eig_min_per_inlier",
    "gmapping_score_norm",
    "condition_number",
    "iterations",
    "converged",
)
"""Quality metrics that mean the same for any sensor and robot speed.

The hybrid CNN's `scanguard.detect.model.METRIC_FEATURES` plus the (dimensionless) Hessian
``condition_number``: per-point residuals, fractions (inlier ratio, per-beam GMapping score),
the smallest eigenvalue per inlier, and the solver's iteration count and convergence flag.
"""

SCALE_DEPENDENT_METRICS_FEATURES: tuple[str, ...] = (
    "eig_min",
    "eig_mid",
    "eig_max",
    "n_source",
    "n_target",
    "n_inliers",
    "translation",
    "rotation",
    "gmapping_score",
)
"""Metrics whose values depend on the sensor (beam count) or the robot's step size.

Raw point counts, raw Hessian eigenvalues and the raw GMapping score grow with the number of
beams; ``translation`` / ``rotation`` with the speed. A model trained on them in simulation
rejects every pair of a 180-beam SICK log with ~1 m steps, so no default detector reads them.
"""

DEFAULT_METRICS_FEATURES: tuple[str, ...] = SCALE_FREE_METRICS_FEATURES
"""Quality metrics the metrics model uses when present (never errors or labels: no leakage).

Only scale-free ones (`SCALE_FREE_METRICS_FEATURES`), so a model fitted on simulated pairs
means the same on a real robot."""

LEGACY_METRICS_FEATURES: tuple[str, ...] = (
    "iterations",
    "converged",
    "mean_residual",
    "median_residual",
    "inlier_ratio",
    "eig_min",
    "eig_mid",
    "eig_max",
    "condition_number",
    "eig_min_per_inlier",
    "n_source",
    "n_target",
    "n_inliers",
    "translation",
    "rotation",
    "ok",
    "gmapping_score",
    "gmapping_score_norm",
)
"""Every stored quality metric: the metrics model's former default feature set.

Kept to reproduce old figures (``MetricsModelDetector(LEGACY_METRICS_FEATURES)``) and as the
list of ICP metrics a harvest stores. It includes `SCALE_DEPENDENT_METRICS_FEATURES`, so a
model on it does **not** transfer between sensors or robots (on real CARMEN logs the one fitted
on simulated pairs rejected every pair)."""


def with_derived_features(features: Mapping[str, ArrayLike]) -> dict[str, FloatArray]:
    """Add features that can be derived from stored ones, as float64 columns.

    * ``gmapping_score_norm = gmapping_score / n_source`` (the dataset stores only the raw sum;
      ``n_source`` is the number of current-scan points given to the matcher).
    * ``eig_min_per_inlier = eig_min / n_inliers``.

    Existing columns are never overwritten.
    """
    out = {k: np.asarray(v, dtype=np.float64) for k, v in features.items()}
    with np.errstate(divide="ignore", invalid="ignore"):
        if "gmapping_score_norm" not in out and {"gmapping_score", "n_source"} <= out.keys():
            n = out["n_source"]
            out["gmapping_score_norm"] = np.where(n > 0, out["gmapping_score"] / n, 0.0)
        if "eig_min_per_inlier" not in out and {"eig_min", "n_inliers"} <= out.keys():
            n = out["n_inliers"]
            out["eig_min_per_inlier"] = np.where(n > 0, out["eig_min"] / n, 0.0)
    return out


def _columns(features: FeaturesLike, names: Sequence[str] | None, who: str) -> FloatArray:
    """``(N, K)`` float64 matrix of the named columns (or of a raw array)."""
    if isinstance(features, Mapping):
        if names is None:
            raise ModelError(f"{who}: feature names are needed to read a feature mapping")
        cols = with_derived_features(features)
        missing = [n for n in names if n not in cols]
        if missing:
            raise ModelError(f"{who}: missing feature(s) {missing}; available: {sorted(cols)}")
        arr = np.stack([cols[n].reshape(-1) for n in names], axis=1) if names else None
        if arr is None:
            raise ModelError(f"{who}: no features selected")
        return arr
    arr = np.asarray(features, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ModelError(f"{who}: features must be a mapping or a 1-D/2-D array, got {arr.shape}")
    if names is not None and arr.shape[1] != len(names):
        raise ModelError(
            f"{who}: expected {len(names)} feature column(s) {list(names)}, got {arr.shape[1]}"
        )
    return arr


def _labels(labels: ArrayLike, n: int, who: str) -> NDArray[np.int64]:
    y = np.asarray(labels).reshape(-1)
    if len(y) != n:
        raise ModelError(f"{who}: {n} feature rows but {len(y)} labels")
    if not np.isin(y, (-1, 0, 1)).all():
        raise ModelError(f"{who}: labels must be 0 (normal), 1 (fault) or -1 (ambiguous)")
    return y.astype(np.int64)


def _check_two_classes(y: NDArray[np.int64], who: str) -> None:
    if not ((y == 0).any() and (y == 1).any()):
        raise ModelError(
            f"{who}: training needs both normal (0) and fault (1) labels; got "
            f"{int((y == 0).sum())} normal and {int((y == 1).sum())} fault"
        )


# --------------------------------------------------------------------------------------------
# Detectors
# --------------------------------------------------------------------------------------------


@runtime_checkable
class Detector(Protocol):
    """The common API of every baseline detector."""

    name: str

    @property
    def threshold(self) -> float:
        """Decision threshold (feature units for `ThresholdDetector`, probability otherwise)."""
        ...

    def fit(
        self,
        features: FeaturesLike,
        labels: ArrayLike,
        *,
        select: tuple[FeaturesLike, ArrayLike] | None = None,
    ) -> Detector:
        """Tune on training data (labels -1 are ignored), threshold on ``select``; returns self."""
        ...

    def select_threshold(self, features: FeaturesLike, labels: ArrayLike) -> float:
        """Choose the operating threshold on labelled pairs by `THRESHOLD_RULE`; returns it."""
        ...

    def predict_proba(self, features: FeaturesLike) -> FloatArray:
        """``(N,)`` fault scores in ``[0, 1]``; higher = more likely a fault."""
        ...

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """``(N,)`` 0 = normal, 1 = fault."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state of the fitted detector."""
        ...


Criterion = Literal["balanced_accuracy", "accuracy"]
Selection = tuple[FeaturesLike, ArrayLike]
"""A selection set: features and labels of pairs the detector is not fitted on."""

THRESHOLD_RULE = "max balanced accuracy on the selection split"
"""How every detector's operating threshold is chosen: the CNN's rule
(`scanguard.scoring.choose_threshold`), on pairs not used to fit the detector."""


def _best_threshold(
    score: FloatArray, y: NDArray[np.int64], criterion: Criterion
) -> tuple[float, float]:
    """Threshold ``t`` on an oriented score (fault iff ``score > t``) maximising ``criterion``.

    Candidates are midpoints between consecutive distinct finite scores plus one below and one
    above all of them; among equally good candidates the middle one is taken, so a clean gap
    between the classes gets its centre. Returns ``(t, criterion value)``.
    """
    pos = np.sort(score[y == 1])
    neg = np.sort(score[y == 0])
    finite = np.unique(score[np.isfinite(score)])
    if len(finite) == 0:
        cand = np.array([0.0])
    else:
        mids = (finite[:-1] + finite[1:]) / 2.0
        cand = np.concatenate([[finite[0] - 1.0], mids, [finite[-1] + 1.0]])
    tp = len(pos) - np.searchsorted(pos, cand, side="right")
    tn = np.searchsorted(neg, cand, side="right")
    if criterion == "balanced_accuracy":
        value = 0.5 * (tp / len(pos) + tn / len(neg))
    else:
        value = (tp + tn) / (len(pos) + len(neg))
    best = np.flatnonzero(value >= value.max() - 1e-12)
    i = int(best[len(best) // 2])
    return float(cand[i]), float(value[i])


class ThresholdDetector:
    """Fault iff one quality metric is above (``"high"``) or below (``"low"``) a threshold.

    The threshold maximises the balanced accuracy (default) or the accuracy on the selection
    set given to `fit` (``select``, pairs it is not fitted on: the CNN's rule, see
    `THRESHOLD_RULE`), else on the fitting data; among equally good thresholds the middle one
    is taken (for a monotone score this is `scanguard.scoring.choose_threshold` with
    its ties resolved to the centre of the tied range). Non-finite feature values (a failed
    match has NaN residuals) count as faults.
    `predict_proba` is a strictly monotone squashing of the raw feature (``0.5`` at the
    threshold), not a calibrated probability: its ROC curve equals that of the raw feature
    (`score` returns the raw feature in fault-positive orientation).

    Args:
        feature: Feature name (a key of ``MatchResult.metrics()``, ``gmapping_score``, ...).
        direction: ``"high"`` if large values mean fault, ``"low"`` if small values do.
        name: Display name (defaults to ``feature``).
        criterion: ``"balanced_accuracy"`` or ``"accuracy"``.
    """

    def __init__(
        self,
        feature: str,
        direction: Literal["high", "low"],
        *,
        name: str | None = None,
        criterion: Criterion = "balanced_accuracy",
    ) -> None:
        if direction not in ("high", "low"):
            raise ConfigError(f"ThresholdDetector({feature}): direction must be 'high' or 'low'")
        if criterion not in ("balanced_accuracy", "accuracy"):
            raise ConfigError(f"ThresholdDetector({feature}): unknown criterion {criterion!r}")
        self.feature = feature
        self.direction: Literal["high", "low"] = direction
        self.name = name or feature
        self.criterion: Criterion = criterion
        self._t: float | None = None  # threshold on the oriented score
        self.scale = 1.0
        self.train_score: float | None = None
        self.select_score: float | None = None
        self.n_select = 0

    @property
    def fitted(self) -> bool:
        """Whether `fit` (or `load_detector`) has set the threshold."""
        return self._t is not None

    @property
    def threshold(self) -> float:
        """The threshold in the feature's own units (NaN until fitted)."""
        if self._t is None:
            return math.nan
        return self._t if self.direction == "high" else -self._t

    def _oriented_threshold(self) -> float:
        if self._t is None:
            raise ModelError(f"detector {self.name!r} is not fitted")
        return self._t

    def score(self, features: FeaturesLike) -> FloatArray:
        """Raw feature in fault-positive orientation (``-x`` for ``"low"``); NaN -> +inf."""
        x = _columns(features, [self.feature], f"detector {self.name!r}")[:, 0]
        s = x if self.direction == "high" else -x
        return np.where(np.isnan(s), np.inf, s)

    def _labelled_scores(
        self, features: FeaturesLike, labels: ArrayLike, what: str = ""
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """Oriented scores and labels of the labelled (0/1) rows; both classes required."""
        who = f"detector {self.name!r}{what}"
        s = self.score(features)
        y = _labels(labels, len(s), who)
        keep = y >= 0
        _check_two_classes(y[keep], who)
        return s[keep], y[keep]

    def _criterion(self, s: FloatArray, y: NDArray[np.int64]) -> float:
        pred = (s > self._oriented_threshold()).astype(np.int64)
        if self.criterion == "balanced_accuracy":
            return balanced_accuracy(y, pred, 0.5)
        return float(np.mean(pred == y))

    def select_threshold(self, features: FeaturesLike, labels: ArrayLike) -> float:
        """Choose the threshold on labelled pairs (labels -1 ignored) and return it.

        The rule of `THRESHOLD_RULE`; ``select_score`` is the criterion value reached.
        """
        s, y = self._labelled_scores(features, labels, " (selection set)")
        self._t, self.select_score = _best_threshold(s, y, self.criterion)
        self.n_select = len(y)
        return self.threshold

    def fit(
        self,
        features: FeaturesLike,
        labels: ArrayLike,
        *,
        select: Selection | None = None,
    ) -> ThresholdDetector:
        """Fit on training data (labels -1 are ignored); the threshold on ``select`` if given.

        Args:
            features: Feature columns of the fitting pairs.
            labels: Their labels.
            select: ``(features, labels)`` of pairs not used for fitting (the validation split)
                on which `select_threshold` chooses the threshold; None = the fitting pairs.
        """
        s, y = self._labelled_scores(features, labels)
        if select is None:
            self.select_threshold(features, labels)
        else:
            self.select_threshold(*select)
        self.train_score = self._criterion(s, y)
        fin = s[np.isfinite(s)]
        if len(fin) >= 2:
            q75, q25 = np.percentile(fin, [75, 25])
            spread = (q75 - q25) / 1.349 or float(np.std(fin))
        else:
            spread = 0.0
        self.scale = float(spread) if spread > 0 else 1.0
        log.debug(
            "%s: threshold %s %.6g (%s %.4f on %d selection pairs, %.4f on %d fitting pairs)",
            self.name,
            ">" if self.direction == "high" else "<",
            self.threshold,
            self.criterion,
            self.select_score,
            self.n_select,
            self.train_score,
            len(y),
        )
        return self

    def predict_proba(self, features: FeaturesLike) -> FloatArray:
        """Monotone fault score in ``(0, 1)`` (``> 0.5`` iff past the threshold; inf -> 1)."""
        t = self._oriented_threshold()
        s = self.score(features)
        with np.errstate(invalid="ignore", over="ignore"):
            z = (s - t) / self.scale
        # arctan, unlike a logistic, does not saturate to exactly 0/1 for large |z|, so the
        # ranking (and the ROC curve) of the raw feature is preserved.
        return np.asarray(0.5 + np.arctan(z) / np.pi, dtype=np.float64)

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """0 = normal, 1 = fault."""
        t = self._oriented_threshold()
        return (self.score(features) > t).astype(np.int64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state."""
        return {
            "type": "threshold",
            "name": self.name,
            "feature": self.feature,
            "direction": self.direction,
            "criterion": self.criterion,
            "threshold": None if self._t is None else self.threshold,
            "scale": self.scale,
            "train_score": self.train_score,
            "select_score": self.select_score,
            "n_select": self.n_select,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ThresholdDetector:
        """Rebuild from `to_dict` output."""
        det = cls(
            data["feature"], data["direction"], name=data["name"], criterion=data["criterion"]
        )
        thr = data.get("threshold")
        if thr is not None:
            det._t = float(thr) if det.direction == "high" else -float(thr)
        det.scale = float(data.get("scale", 1.0))
        det.train_score = data.get("train_score")
        det.select_score = data.get("select_score")
        det.n_select = int(data.get("n_select") or 0)
        return det

    def __repr__(self) -> str:
        thr = f"{self.threshold:.6g}" if self.fitted else "unfitted"
        op = ">" if self.direction == "high" else "<"
        return f"ThresholdDetector({self.name!r}: fault if {self.feature} {op} {thr})"


_THREADPOOLS: Any = None


def _single_thread() -> Any:
    """Limit OpenMP/BLAS to one thread while fitting or predicting.

    The models are tiny and machines are often shared, so threads cost more than they save.
    """
    global _THREADPOOLS
    if _THREADPOOLS is None:
        from threadpoolctl import ThreadpoolController

        # Scanning the loaded libraries (what `threadpool_limits` does on every call) costs
        # ~4 ms, more than a one-pair prediction; the pools are those of numpy/scipy/sklearn,
        # all loaded by the time a model is fitted or unpickled.
        _THREADPOOLS = ThreadpoolController()
    return _THREADPOOLS.limit(limits=1)


class MetricsModelDetector:
    """A small classifier over all ICP quality metrics together.

    ``kind="gbm"`` (default) is sklearn's ``HistGradientBoostingClassifier`` (shallow trees,
    fixed seed, no early stopping, NaN handled natively); ``kind="logistic"`` is a logistic
    regression on standardised features after a signed ``log1p`` compression (condition numbers
    span many decades) with NaN imputed by the training median. Both weight the classes
    "balanced". ``+-inf`` values become NaN.

    The model is fitted on the fitting pairs; its probability threshold is then chosen by the
    CNN's rule, `scanguard.scoring.choose_threshold` (max balanced accuracy, ties ->
    nearest 0.5), on the selection set given to `fit` (pairs the model was not fitted on), else
    on the fitting pairs. A pair is a fault when its probability is ``>= threshold``.

    Args:
        features: Feature names to use; None = those of `DEFAULT_METRICS_FEATURES` (scale-free
            only) present, with a finite value, at fit time (with a mapping) or every column
            (with an array). Pass
            `LEGACY_METRICS_FEATURES` to reproduce the former, non-transferring model.
        kind: ``"gbm"`` or ``"logistic"``.
        name: Display name.
        random_state: Seed of the gradient boosting.
    """

    def __init__(
        self,
        features: Sequence[str] | None = None,
        *,
        kind: Literal["gbm", "logistic"] = "gbm",
        name: str = "metrics-model",
        random_state: int = 0,
    ) -> None:
        if kind not in ("gbm", "logistic"):
            raise ConfigError(
                f"MetricsModelDetector: kind must be 'gbm' or 'logistic', not {kind!r}"
            )
        self.features: list[str] | None = None if features is None else list(features)
        self.kind: Literal["gbm", "logistic"] = kind
        self.name = name
        self.random_state = random_state
        self._threshold = 0.5
        self.model: Any = None
        self.select_score: float | None = None
        self.n_select = 0

    @property
    def threshold(self) -> float:
        """Probability threshold of `predict`."""
        return self._threshold

    @threshold.setter
    def threshold(self, value: float) -> None:
        self._threshold = float(value)

    def _matrix(self, features: FeaturesLike) -> FloatArray:
        x = _columns(features, self.features, f"detector {self.name!r}")
        x = np.where(np.isfinite(x), x, np.nan)
        if self.kind == "logistic":
            x = np.sign(x) * np.log1p(np.abs(x))
        return x

    def _build(self) -> Any:
        if self.kind == "gbm":
            from sklearn.ensemble import HistGradientBoostingClassifier

            return HistGradientBoostingClassifier(
                max_iter=100,
                learning_rate=0.1,
                max_leaf_nodes=15,
                l2_regularization=1.0,
                class_weight="balanced",
                early_stopping=False,
                random_state=self.random_state,
            )
        from sklearn.impute import SimpleImputer
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        return make_pipeline(
            SimpleImputer(strategy="median", keep_empty_features=True),
            StandardScaler(),
            LogisticRegression(class_weight="balanced", max_iter=2000),
        )

    def select_threshold(self, features: FeaturesLike, labels: ArrayLike) -> float:
        """Choose the probability threshold on labelled pairs (labels -1 ignored); return it.

        `scanguard.scoring.choose_threshold` on the model's fault probabilities, the
        rule of the CNN's operating threshold; ``select_score`` is the balanced accuracy there.

        Raises:
            ModelError: Not fitted, or the pairs lack a class.
        """
        from scanguard.scoring import choose_threshold

        who = f"detector {self.name!r} (selection set)"
        proba = self.predict_proba(features)
        y = _labels(labels, len(proba), who)
        keep = y >= 0
        _check_two_classes(y[keep], who)
        self._threshold = choose_threshold(y[keep], proba[keep])
        self.select_score = balanced_accuracy(y[keep], proba[keep] >= self._threshold, 0.5)
        self.n_select = int(keep.sum())
        return self._threshold

    def fit(
        self,
        features: FeaturesLike,
        labels: ArrayLike,
        *,
        select: Selection | None = None,
    ) -> MetricsModelDetector:
        """Train on the fitting pairs (labels -1 are ignored); the threshold on ``select``.

        Args:
            features: Feature columns of the fitting pairs (the training split).
            labels: Their labels.
            select: ``(features, labels)`` of pairs not used for fitting (the validation split)
                on which `select_threshold` chooses the threshold; None = the fitting pairs.
        """
        who = f"detector {self.name!r}"
        if self.features is None:
            if isinstance(features, Mapping):
                available = with_derived_features(features)
                # a metric the matcher never fills (all NaN) carries nothing, and breaks the
                # gradient boosting's binning
                self.features = [
                    f
                    for f in DEFAULT_METRICS_FEATURES
                    if f in available and np.isfinite(available[f]).any()
                ]
            else:
                arr = np.asarray(features)
                ncol = 1 if arr.ndim == 1 else arr.shape[1]
                self.features = [f"f{i}" for i in range(ncol)]
            if not self.features:
                raise ModelError(f"{who}: none of {list(DEFAULT_METRICS_FEATURES)} is available")
        x = self._matrix(features)
        y = _labels(labels, len(x), who)
        keep = y >= 0
        x, y = x[keep], y[keep]
        _check_two_classes(y, who)
        with _single_thread():
            self.model = self._build().fit(x, y)
        if select is None:
            self.select_threshold(features, labels)
        else:
            self.select_threshold(*select)
        log.debug(
            "%s: %s on %d pairs, features %s, threshold %.4g (balanced accuracy %.4f on %d "
            "selection pairs)",
            self.name,
            self.kind,
            len(y),
            self.features,
            self._threshold,
            self.select_score,
            self.n_select,
        )
        return self

    def predict_proba(self, features: FeaturesLike) -> FloatArray:
        """Fault probability ``(N,)``."""
        if self.model is None:
            raise ModelError(f"detector {self.name!r} is not fitted")
        with _single_thread():
            proba = self.model.predict_proba(self._matrix(features))[:, 1]
        return np.asarray(proba, dtype=np.float64)

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """0 = normal, 1 = fault (probability >= `threshold`)."""
        return (self.predict_proba(features) >= self._threshold).astype(np.int64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state (the sklearn model pickled as base64)."""
        import sklearn

        return {
            "type": "metrics-model",
            "name": self.name,
            "kind": self.kind,
            "features": self.features,
            "threshold": self._threshold,
            "threshold_rule": THRESHOLD_RULE,
            "select_score": self.select_score,
            "n_select": self.n_select,
            "random_state": self.random_state,
            "sklearn_version": sklearn.__version__,
            "model_pickle": None
            if self.model is None
            else base64.b64encode(pickle.dumps(self.model, protocol=4)).decode("ascii"),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MetricsModelDetector:
        """Rebuild from `to_dict` output (unpickles the model: trusted files only)."""
        det = cls(
            data["features"],
            kind=data["kind"],
            name=data["name"],
            random_state=int(data.get("random_state", 0)),
        )
        det.threshold = float(data.get("threshold", 0.5))
        det.select_score = data.get("select_score")
        det.n_select = int(data.get("n_select") or 0)
        blob = data.get("model_pickle")
        if blob is not None:
            det.model = pickle.loads(base64.b64decode(blob))
        return det

    def __repr__(self) -> str:
        state = "fitted" if self.model is not None else "unfitted"
        return f"MetricsModelDetector({self.name!r}, {self.kind}, {state})"


# --------------------------------------------------------------------------------------------
# Registry and persistence
# --------------------------------------------------------------------------------------------

# Every feature read here is in SCALE_FREE_METRICS_FEATURES (checked by the tests): a baseline
# fitted on simulated pairs means the same on a real robot.
BASELINES: dict[str, Callable[[], Detector]] = {
    "residual": lambda: ThresholdDetector("mean_residual", "high", name="residual"),
    "overlap": lambda: ThresholdDetector("inlier_ratio", "low", name="overlap"),
    # Per inlier: the raw eigenvalue grows with the number of matched points, which differs
    # between sensors; the plain ``eig_min`` is available as ThresholdDetector("eig_min", "low").
    "degeneracy": lambda: ThresholdDetector("eig_min_per_inlier", "low", name="degeneracy"),
    # Per beam: the raw GMapping score grows with the number of beams.
    "gmapping": lambda: ThresholdDetector("gmapping_score_norm", "low", name="gmapping"),
    "metrics-model": lambda: MetricsModelDetector(name="metrics-model"),
}
"""Default baselines of the evaluation table: name -> factory of an unfitted detector.

All read only scale-free features (`SCALE_FREE_METRICS_FEATURES`) and choose their threshold
by `THRESHOLD_RULE` when fitted with a selection set."""

ODOMETRY_BASELINES: dict[str, Callable[[], Detector]] = {
    # the chi-like test a careful user with wheel odometry writes first: the larger of the
    # translational and rotational disagreement, in standard deviations of the noise model
    "odometry": lambda: ThresholdDetector("odom_max_z", "high", name="odometry"),
    "metrics+odometry": lambda: MetricsModelDetector(
        [*SCALE_FREE_METRICS_FEATURES, *ODOMETRY_FEATURES], name="metrics+odometry"
    ),
}
"""Classical detectors that also read the odometry disagreement (`scanguard.pairs.odometry`).

They need the odometry features of a pair store (`scanguard.detect.evaluate.store_features`),
so they take part in evaluations, not in ``run``'s baseline instance; on pairs without
odometry the features are 0 and the mask says so."""


def make_baseline(name: str) -> Detector:
    """A new, unfitted baseline from `BASELINES` or `ODOMETRY_BASELINES`.

    Raises:
        ConfigError: Unknown name (the message lists the known ones).
    """
    known = {**BASELINES, **ODOMETRY_BASELINES}
    try:
        return known[name]()
    except KeyError:
        raise ConfigError(f"unknown baseline {name!r}; known: {', '.join(sorted(known))}") from None


def save_detector(detector: Detector, path: str | Path) -> Path:
    """Write a (fitted) detector as JSON, atomically."""
    p = Path(path)
    atomic_write_text(p, json.dumps(detector.to_dict(), indent=1))
    return p


def load_detector(path: str | Path) -> Detector:
    """Load a detector written by `save_detector`.

    Raises:
        ModelError: Missing, not JSON, or not a detector file.
    """
    p = Path(path)
    if not p.is_file():
        raise ModelError(f"{p}: detector file not found")
    try:
        data = json.loads(p.read_text())
        kind = data["type"]
        if kind == "threshold":
            return ThresholdDetector.from_dict(data)
        if kind == "metrics-model":
            return MetricsModelDetector.from_dict(data)
    except (ValueError, KeyError, TypeError, pickle.UnpicklingError) as exc:
        raise ModelError(f"{p}: not a valid detector file ({exc})") from None
    raise ModelError(f"{p}: unknown detector type {kind!r}")
