"""Fitted classifiers stored as plain arrays and evaluated with numpy: no pickle, no sklearn.

scikit-learn fits the classical detectors' models (`MetricsModelDetector`), but a pickled
estimator only loads in the scikit-learn that wrote it. `export_sklearn` copies what
prediction needs out of a fitted estimator into a `PortableModel`, whose ``predict_proba``
reproduces sklearn's ``predict_proba(x)[:, 1]`` exactly (same comparisons, same order of
additions), and whose ``to_dict`` / `model_from_dict` is plain JSON (numbers and lists).

Two kinds:

* ``hist-gbm``: `HistGradientBoostingClassifier` (binary, numerical features). Raw score =
  the baseline plus, tree after tree, the leaf value each row reaches; a node sends a row left
  when ``x <= threshold`` (float64 against float64, as sklearn's predictor does on raw data)
  and a NaN the way the node learned for missing values. Probability = ``expit(raw)``.
* ``logistic``: an optional NaN imputation (fill values), optional standardisation (mean,
  scale) and a binary `LogisticRegression` (coefficients, intercept); probability =
  ``expit(x @ coef.T + intercept)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.special import expit

from scanguard.errors import ModelError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# rows evaluated at once by the trees: bounds the (rows x trees) index arrays to a few MB
_CHUNK = 4096


class PortableModel(Protocol):
    """A fitted binary classifier that needs only numpy (and scipy's ``expit``)."""

    kind: str
    n_features: int

    def predict_proba(self, x: FloatArray) -> FloatArray:
        """Probability of class 1, ``(N,)``, for a float64 matrix ``(N, n_features)``."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON state (numbers and lists)."""
        ...


def _check_matrix(x: Any, n_features: int) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != n_features:
        raise ModelError(
            f"the model reads {n_features} feature columns, got an array of shape {arr.shape}"
        )
    return arr


# --------------------------------------------------------------------------------------------
# gradient boosting
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Tree:
    """One regression tree; node 0 is the root, a leaf has ``left == right == -1``.

    Attributes:
        left: Left child of each node (-1 at a leaf).
        right: Right child of each node (-1 at a leaf).
        feature: Column each split reads (0 at a leaf).
        threshold: A row goes left when ``x[feature] <= threshold``.
        missing_left: Whether NaN goes left.
        value: Leaf value (the learning rate already applied, as sklearn stores it).
    """

    left: IntArray
    right: IntArray
    feature: IntArray
    threshold: FloatArray
    missing_left: NDArray[np.bool_]
    value: FloatArray

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON arrays."""
        return {
            "left": self.left.tolist(),
            "right": self.right.tolist(),
            "feature": self.feature.tolist(),
            "threshold": self.threshold.tolist(),
            "missing_left": [int(b) for b in self.missing_left],
            "value": self.value.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], n_features: int) -> Tree:
        """Rebuild and check the structure (children after their parent, features in range).

        Raises:
            ModelError: Ragged arrays, a child index out of order, a feature out of range or a
                non-finite leaf value.
        """
        arrays = {k: np.asarray(data[k]) for k in Tree.__dataclass_fields__}
        n = len(arrays["left"])
        if n == 0 or any(a.shape != (n,) for a in arrays.values()):
            raise ModelError("a tree's arrays are empty or of different lengths")
        ints = {k: _int_array(arrays[k], k) for k in ("left", "right", "feature")}
        left, right, feature = ints["left"], ints["right"], ints["feature"]
        threshold = np.asarray(arrays["threshold"], dtype=np.float64)
        value = np.asarray(arrays["value"], dtype=np.float64)
        leaf = left < 0
        idx = np.arange(n)
        # children strictly after their parent: every walk ends at a leaf within n steps
        if np.any(leaf != (right < 0)) or np.any(
            ~leaf & ((left <= idx) | (right <= idx) | (left >= n) | (right >= n))
        ):
            raise ModelError("a tree's child indices are out of order or out of range")
        if np.any(~leaf & ((feature < 0) | (feature >= n_features))):
            raise ModelError(f"a tree splits on a feature outside 0..{n_features - 1}")
        if np.any(~leaf & np.isnan(threshold)) or not np.all(np.isfinite(value[leaf])):
            raise ModelError("a tree has a NaN threshold or a non-finite leaf value")
        return cls(left, right, feature, threshold, arrays["missing_left"].astype(bool), value)


def _int_array(a: NDArray[Any], name: str) -> IntArray:
    if a.dtype.kind not in "iu":
        raise ModelError(f"a tree's {name!r} array is not integers")
    return a.astype(np.int64)


class HistGBMModel:
    """Binary gradient boosting (`HistGradientBoostingClassifier`'s prediction).

    Args:
        baseline: Initial raw score (log-odds).
        trees: The trees, in the order they were fitted (their values are added in it).
        n_features: Number of feature columns.
    """

    kind = "hist-gbm"

    def __init__(self, baseline: float, trees: Sequence[Tree], n_features: int) -> None:
        if not trees:
            raise ModelError("a gradient boosting model needs at least one tree")
        self.baseline = float(baseline)
        self.trees = list(trees)
        self.n_features = int(n_features)
        # all trees in one node table, leaves pointing at themselves: every row of every tree
        # then advances in lock-step for `_depth` steps (vectorised over rows and trees)
        sizes = [len(t.left) for t in self.trees]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self._roots = offsets
        left, right = [], []
        for t, o in zip(self.trees, offsets, strict=True):
            own = np.arange(len(t.left)) + o
            left.append(np.where(t.left < 0, own, t.left + o))
            right.append(np.where(t.right < 0, own, t.right + o))
        self._left = np.concatenate(left)
        self._right = np.concatenate(right)
        self._feature = np.concatenate([t.feature for t in self.trees])
        self._threshold = np.concatenate([t.threshold for t in self.trees])
        self._missing_left = np.concatenate([t.missing_left for t in self.trees])
        self._value = np.concatenate([t.value for t in self.trees])
        self._depth = max(_depth(t) for t in self.trees)

    def raw_score(self, x: FloatArray) -> FloatArray:
        """Log-odds ``(N,)``: the baseline, then each tree's leaf value added in turn."""
        x = _check_matrix(x, self.n_features)
        out = np.empty(len(x))
        for start in range(0, len(x), _CHUNK):
            out[start : start + _CHUNK] = self._raw_chunk(x[start : start + _CHUNK])
        return out

    def _raw_chunk(self, x: FloatArray) -> FloatArray:
        n = len(x)
        node = np.broadcast_to(self._roots, (n, len(self._roots))).copy()
        rows = np.arange(n)[:, None]
        for _ in range(self._depth):
            v = x[rows, self._feature[node]]
            with np.errstate(invalid="ignore"):
                go_left = np.where(
                    np.isnan(v), self._missing_left[node], v <= self._threshold[node]
                )
            node = np.where(go_left, self._left[node], self._right[node])
        # one column per tree after the baseline; add.accumulate adds strictly left to right,
        # as sklearn's `raw += tree.predict(X)` loop does (no pairwise summation)
        terms = np.concatenate([np.full((n, 1), self.baseline), self._value[node]], axis=1)
        return np.asarray(np.add.accumulate(terms, axis=1)[:, -1], dtype=np.float64)

    def predict_proba(self, x: FloatArray) -> FloatArray:
        """Probability of class 1, ``(N,)``."""
        return np.asarray(expit(self.raw_score(x)), dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON state."""
        return {
            "kind": self.kind,
            "n_features": self.n_features,
            "baseline": self.baseline,
            "trees": [t.to_dict() for t in self.trees],
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> HistGBMModel:
        """Rebuild from `to_dict` output (checked; see `Tree.from_dict`)."""
        n_features = int(data["n_features"])
        trees = data["trees"]
        if not isinstance(trees, list):
            raise ModelError("'trees' is not a list")
        baseline = float(data["baseline"])
        if not math.isfinite(baseline):
            raise ModelError("the baseline score is not finite")
        return cls(baseline, [Tree.from_dict(t, n_features) for t in trees], n_features)


def _depth(tree: Tree) -> int:
    """Longest root-to-leaf path (in edges); children come after parents, so one pass."""
    depth = np.zeros(len(tree.left), dtype=np.int64)
    for i in range(len(tree.left)):
        if tree.left[i] >= 0:
            depth[tree.left[i]] = depth[tree.right[i]] = depth[i] + 1
    return int(depth.max())


# --------------------------------------------------------------------------------------------
# logistic regression
# --------------------------------------------------------------------------------------------


class LogisticModel:
    """Binary logistic regression after an optional imputation and standardisation.

    Args:
        coef: Coefficients ``(n_features,)``.
        intercept: Intercept.
        fill: Value replacing NaN in each column (None = no imputation).
        mean: Mean subtracted from each column (None = no standardisation).
        scale: Divisor of each column after the mean (None = 1).
    """

    kind = "logistic"

    def __init__(
        self,
        coef: Sequence[float] | FloatArray,
        intercept: float,
        fill: Sequence[float] | FloatArray | None = None,
        mean: Sequence[float] | FloatArray | None = None,
        scale: Sequence[float] | FloatArray | None = None,
    ) -> None:
        self.coef = np.asarray(coef, dtype=np.float64).reshape(1, -1)
        self.n_features = self.coef.shape[1]
        self.intercept = np.array([float(intercept)])

        def vec(v: Sequence[float] | FloatArray | None, name: str) -> FloatArray | None:
            if v is None:
                return None
            a = np.asarray(v, dtype=np.float64)
            if a.shape != (self.n_features,) or not np.all(np.isfinite(a)):
                raise ModelError(f"logistic model: {name!r} is not {self.n_features} finite values")
            return a

        self.fill = vec(fill, "fill")
        self.mean = vec(mean, "mean")
        self.scale = vec(scale, "scale")
        if not np.all(np.isfinite(self.coef)) or not np.isfinite(self.intercept[0]):
            raise ModelError("logistic model: non-finite coefficients")

    def predict_proba(self, x: FloatArray) -> FloatArray:
        """Probability of class 1, ``(N,)``."""
        x = _check_matrix(x, self.n_features).copy()
        if self.fill is not None:
            x = np.where(np.isnan(x), self.fill, x)
        # in place and in this order, as sklearn's StandardScaler.transform does
        if self.mean is not None:
            x -= self.mean
        if self.scale is not None:
            x /= self.scale
        scores = x @ self.coef.T + self.intercept
        return np.asarray(expit(scores.reshape(-1)), dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON state."""

        def lst(a: FloatArray | None) -> list[float] | None:
            return None if a is None else a.tolist()

        return {
            "kind": self.kind,
            "n_features": self.n_features,
            "coef": self.coef[0].tolist(),
            "intercept": float(self.intercept[0]),
            "fill": lst(self.fill),
            "mean": lst(self.mean),
            "scale": lst(self.scale),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LogisticModel:
        """Rebuild from `to_dict` output."""
        model = cls(
            data["coef"], data["intercept"], data.get("fill"), data.get("mean"), data.get("scale")
        )
        if model.n_features != int(data["n_features"]):
            raise ModelError("logistic model: 'coef' does not match 'n_features'")
        return model


# --------------------------------------------------------------------------------------------
# reading and exporting
# --------------------------------------------------------------------------------------------


def model_from_dict(data: Any) -> PortableModel:
    """A `PortableModel` from its ``to_dict`` output.

    Raises:
        ModelError: Not a model of a known kind, or a malformed one.
    """
    if not isinstance(data, Mapping):
        raise ModelError(f"the model entry is a {type(data).__name__}, not a model")
    kind = data.get("kind")
    try:
        if kind == HistGBMModel.kind:
            return HistGBMModel.from_dict(data)
        if kind == LogisticModel.kind:
            return LogisticModel.from_dict(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"malformed {kind} model ({type(exc).__name__}: {exc})") from None
    raise ModelError(f"unknown model kind {kind!r} (known: hist-gbm, logistic)")


def export_sklearn(estimator: Any) -> PortableModel:
    """Copy a fitted sklearn estimator into a `PortableModel` (sklearn itself is not imported).

    Supported: a binary `HistGradientBoostingClassifier` on numerical features; a binary
    `LogisticRegression`, alone or at the end of a `Pipeline` of `SimpleImputer` (NaN) and
    `StandardScaler` steps.

    Raises:
        ModelError: Another estimator, more than two classes, categorical features.
    """
    name = type(estimator).__name__
    classes = getattr(estimator, "classes_", None)
    if classes is not None and [int(c) for c in classes] != [0, 1]:
        raise ModelError(f"{name}: classes {list(classes)}, expected [0, 1]")
    if name == "HistGradientBoostingClassifier":
        return _export_hist_gbm(estimator)
    if name == "Pipeline":
        *steps, (_, last) = estimator.steps
        if type(last).__name__ == "LogisticRegression":
            return _export_logistic([s for _, s in steps], last)
    if name == "LogisticRegression":
        return _export_logistic([], estimator)
    raise ModelError(f"cannot store a {name} version-free (hist-gbm or logistic only)")


def _export_hist_gbm(est: Any) -> HistGBMModel:
    if est.n_trees_per_iteration_ != 1:
        raise ModelError("HistGradientBoostingClassifier: more than two classes")
    categorical = getattr(est, "is_categorical_", None)
    if getattr(est, "_preprocessor", None) is not None or (
        categorical is not None and np.any(categorical)
    ):
        raise ModelError("HistGradientBoostingClassifier: categorical features")
    trees = []
    for (predictor,) in est._predictors:
        nodes = predictor.nodes
        leaf = nodes["is_leaf"].astype(bool)
        trees.append(
            Tree(
                left=np.where(leaf, -1, nodes["left"].astype(np.int64)),
                right=np.where(leaf, -1, nodes["right"].astype(np.int64)),
                feature=np.where(leaf, 0, nodes["feature_idx"].astype(np.int64)),
                threshold=np.where(leaf, 0.0, nodes["num_threshold"].astype(np.float64)),
                missing_left=nodes["missing_go_to_left"].astype(bool) & ~leaf,
                value=np.where(leaf, nodes["value"].astype(np.float64), 0.0),
            )
        )
    baseline = np.asarray(est._baseline_prediction, dtype=np.float64).reshape(-1)
    return HistGBMModel(float(baseline[0]), trees, int(est.n_features_in_))


def _export_logistic(steps: list[Any], lr: Any) -> LogisticModel:
    coef = np.asarray(lr.coef_, dtype=np.float64)
    if coef.shape[0] != 1:
        raise ModelError("LogisticRegression: more than two classes")
    fill = mean = scale = None
    for step in steps:
        kind = type(step).__name__
        if kind == "SimpleImputer" and fill is None and mean is None:
            missing = step.missing_values
            if not (isinstance(missing, float) and math.isnan(missing)):
                raise ModelError("SimpleImputer: only missing_values=NaN is supported")
            fill = np.asarray(step.statistics_, dtype=np.float64)
        elif kind == "StandardScaler" and mean is None:
            n = coef.shape[1]
            mean = np.asarray(step.mean_, dtype=np.float64) if step.with_mean else np.zeros(n)
            scale = np.asarray(step.scale_, dtype=np.float64) if step.with_std else np.ones(n)
        else:
            raise ModelError(f"cannot store a pipeline step {kind} version-free")
    return LogisticModel(coef[0], float(np.asarray(lr.intercept_)[0]), fill, mean, scale)


__all__ = [
    "HistGBMModel",
    "LogisticModel",
    "PortableModel",
    "Tree",
    "export_sklearn",
    "model_from_dict",
]
