"""`MetricsModelDetector`: a small classifier over the scale-free quality metrics together."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.detect.baselines.base import (
    DEFAULT_METRICS_FEATURES,
    THRESHOLD_RULE,
    FeaturesLike,
    FloatArray,
    Selection,
    check_labels,
    check_two_classes,
    feature_matrix,
)
from scanguard.detect.baselines.portable import PortableModel, export_sklearn, model_from_dict
from scanguard.detect.features import with_derived_features
from scanguard.errors import ConfigError, ModelError
from scanguard.scoring import balanced_accuracy, choose_threshold

log = logging.getLogger(__name__)

_THREADPOOLS: Any = None


def _single_thread() -> Any:
    """Limit OpenMP/BLAS to one thread while fitting.

    The models are tiny and machines are often shared, so threads cost more than they save.
    """
    global _THREADPOOLS
    if _THREADPOOLS is None:
        from threadpoolctl import ThreadpoolController

        # Scanning the loaded libraries (what `threadpool_limits` does on every call) costs
        # ~4 ms; the pools are those of numpy/scipy/sklearn, all loaded by the time a model is
        # fitted.
        _THREADPOOLS = ThreadpoolController()
    return _THREADPOOLS.limit(limits=1)


LEGACY_MESSAGE = (
    "the model is a pickled scikit-learn estimator (older scanguard), which is no longer loaded; "
    "convert the file once with `python -m scanguard.detect.baselines.convert OLD NEW` "
    "(it unpickles: trusted files only)"
)
"""Why a detector or closure-judge file of the pickled format is refused, and the fix."""


class MetricsModelDetector:
    """A small classifier over all ICP quality metrics together.

    ``kind="gbm"`` (default) is sklearn's ``HistGradientBoostingClassifier`` (shallow trees,
    fixed seed, no early stopping, NaN handled natively); ``kind="logistic"`` is a logistic
    regression on standardised features after a signed ``log1p`` compression (condition numbers
    span many decades) with NaN imputed by the training median. Both weight the classes
    "balanced". ``+-inf`` values become NaN.

    sklearn only fits: the fitted model is then copied into a version-free
    `scanguard.detect.baselines.portable.PortableModel` (plain arrays, evaluated with numpy,
    exactly sklearn's probabilities), which predicts and is what `to_dict` stores; loading a
    detector never unpickles and never imports sklearn.

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
        self.model: PortableModel | None = None
        self.select_score: float | None = None
        self.n_select = 0

    @property
    def threshold(self) -> float:
        """Probability threshold of `predict`."""
        return self._threshold

    @threshold.setter
    def threshold(self, value: float) -> None:
        v = float(value)
        if not 0.0 <= v <= 1.0:  # NaN and Infinity too: such a threshold never (or always) fires
            raise ConfigError(f"{self.name}: threshold must be a probability in [0, 1], got {v}")
        self._threshold = v

    def _matrix(self, features: FeaturesLike) -> FloatArray:
        x = feature_matrix(features, self.features, f"detector {self.name!r}")
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
        who = f"detector {self.name!r} (selection set)"
        proba = self.predict_proba(features)
        y = check_labels(labels, len(proba), who)
        keep = y >= 0
        check_two_classes(y[keep], who)
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
        y = check_labels(labels, len(x), who)
        keep = y >= 0
        x, y = x[keep], y[keep]
        check_two_classes(y, who)
        with _single_thread():
            self.model = export_sklearn(self._build().fit(x, y))
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
        return self.model.predict_proba(self._matrix(features))

    def predict(self, features: FeaturesLike) -> NDArray[np.int64]:
        """0 = normal, 1 = fault (probability >= `threshold`)."""
        return (self.predict_proba(features) >= self._threshold).astype(np.int64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible state (the model as plain arrays; see `portable`)."""
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
            "model": None if self.model is None else self.model.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MetricsModelDetector:
        """Rebuild from `to_dict` output (plain arrays: nothing is unpickled).

        Raises:
            ModelError: A model pickled by an older scanguard (the message says how to convert
                it), or a malformed model.
        """
        if data.get("model_pickle") is not None:
            raise ModelError(LEGACY_MESSAGE)
        det = cls(
            data["features"],
            kind=data["kind"],
            name=data["name"],
            random_state=int(data.get("random_state", 0)),
        )
        thr = float(data.get("threshold", 0.5))
        if not 0.0 <= thr <= 1.0:
            raise ValueError(f"threshold must be a probability in [0, 1], got {thr}")
        det.threshold = thr
        det.select_score = data.get("select_score")
        det.n_select = int(data.get("n_select") or 0)
        if data.get("model") is not None:
            det.model = model_from_dict(data["model"])
            if det.features is not None and det.model.n_features != len(det.features):
                raise ModelError(
                    f"the model reads {det.model.n_features} columns but "
                    f"{len(det.features)} features are named"
                )
        return det

    def __repr__(self) -> str:
        state = "fitted" if self.model is not None else "unfitted"
        return f"MetricsModelDetector({self.name!r}, {self.kind}, {state})"
