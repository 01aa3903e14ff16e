"""`ThresholdDetector`: fault iff one quality metric is above or below a threshold."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.detect.baselines.base import (
    Criterion,
    FeaturesLike,
    FloatArray,
    Selection,
    check_labels,
    check_two_classes,
    feature_matrix,
)
from scanguard.errors import ConfigError, ModelError
from scanguard.scoring import balanced_accuracy

log = logging.getLogger(__name__)


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
        x = feature_matrix(features, [self.feature], f"detector {self.name!r}")[:, 0]
        s = x if self.direction == "high" else -x
        return np.where(np.isnan(s), np.inf, s)

    def _labelled_scores(
        self, features: FeaturesLike, labels: ArrayLike, what: str = ""
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """Oriented scores and labels of the labelled (0/1) rows; both classes required."""
        who = f"detector {self.name!r}{what}"
        s = self.score(features)
        y = check_labels(labels, len(s), who)
        keep = y >= 0
        check_two_classes(y[keep], who)
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
            if not math.isfinite(float(thr)):
                # an infinite threshold never fires, while reports would print it as a number
                raise ValueError(f"threshold must be finite, got {thr}")
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
