"""What every classical detector shares: feature names, API, threshold rule, column helpers.

The `FeatureDetector` protocol is the API of the classifiers that read feature columns (the
judge-facing detector protocol lives in `scanguard.slam`).

``features`` is either a mapping of named columns (the keys of
`scanguard.matching.MatchResult.metrics` plus ``gmapping_score``; derived ratios are added by
`scanguard.detect.features.with_derived_features`) or a 2-D array.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.detect.features import with_derived_features
from scanguard.errors import ModelError

FeaturesLike = Mapping[str, ArrayLike] | ArrayLike
"""Named feature columns ``{name: (N,)}`` or an ``(N, K)`` array (``(N,)`` for one feature)."""


FloatArray = NDArray[np.float64]


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


def feature_matrix(features: FeaturesLike, names: Sequence[str] | None, who: str) -> FloatArray:
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


def check_labels(labels: ArrayLike, n: int, who: str) -> NDArray[np.int64]:
    """Labels as int64 ``(n,)``, checked to be 0, 1 or -1 (``who`` names the caller)."""
    y = np.asarray(labels).reshape(-1)
    if len(y) != n:
        raise ModelError(f"{who}: {n} feature rows but {len(y)} labels")
    if not np.isin(y, (-1, 0, 1)).all():
        raise ModelError(f"{who}: labels must be 0 (normal), 1 (fault) or -1 (ambiguous)")
    return y.astype(np.int64)


def check_two_classes(y: NDArray[np.int64], who: str) -> None:
    """Raise `ModelError` unless ``y`` holds both normal (0) and fault (1) labels."""
    if not ((y == 0).any() and (y == 1).any()):
        raise ModelError(
            f"{who}: training needs both normal (0) and fault (1) labels; got "
            f"{int((y == 0).sum())} normal and {int((y == 1).sum())} fault"
        )


@runtime_checkable
class FeatureDetector(Protocol):
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
    ) -> FeatureDetector:
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
