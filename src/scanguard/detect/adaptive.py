"""An operating point that adapts online: the fault threshold follows this run's normal mode.

The shipped detector ranks pairs well on every domain, but the fault logit of a *normal* pair
sits at a different offset on each (docs/model_card.md, "The ranking transfers; the operating
point does not"), so one calibrated threshold over-flags one recording and under-flags the
next. `AdaptiveThreshold` moves the threshold from the run's own scores, with no first pass
and no reference, the way kiss-icp's adaptive threshold follows the deviation of each
registration from the motion prediction: most matches of a run are normal, so the bulk of its
fault logits is the normal mode, and a fault is a logit far above that mode.

Per judged pair, in the calibrated logit ``u = logit(p)``:

* the threshold is ``tau = mode + k * spread`` of the last ``window`` logits (default: the
  window's 30 % quantile, and 1.4826 times the median absolute deviation of the logits
  below it, never below ``min_spread``: faults sit above the normal mode and barely move
  either; the median, or the half-sample mode, are the alternatives), never below the
  calibrated threshold when ``floor`` is on, and never above ``max_probability``;
* during the warm-up (fewer than ``warmup`` scores seen) it is the calibrated threshold;
* the pair is judged against the threshold of the scores *before* it (causal), then its logit
  joins the window. Cost per pair: O(window) (the window is kept sorted).

It sits behind the `scanguard.slam.judge.Detector` interface unchanged: its ``threshold`` is
the wrapped detector's calibrated one, and the probability it returns is shifted in logit by
the adaptive threshold's distance to that one (``logit(p') = u - tau + logit(t0)``), so
``p' >= t0`` exactly when ``u >= tau``. The judge, the gate and every back end therefore use it
as they use the detector; only the reported probabilities are the shifted ones.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from scanguard.config import YamlModel
from scanguard.errors import ModelError

logger = logging.getLogger(__name__)

OperatingPoint = Literal["fixed", "adaptive"]
Location = Literal["median", "half_sample_mode", "quantile"]
Spread = Literal["mad", "lower_mad"]
#: Normal-consistent scale of the median absolute deviation.
MAD_SCALE = 1.4826
#: Probabilities are clipped this far from 0 and 1 before the logit (a saturated sigmoid).
_EPS = 1e-12


class AdaptiveConfig(YamlModel):
    """Settings of `AdaptiveThreshold` (defaults: chosen leave one recording out, README).

    Attributes:
        location: Where the normal mode is: ``median`` of the window, its
            ``half_sample_mode`` (Bickel's: the densest half, then half of that, ...; it stays
            on the normal mode while faults are fewer than the normal pairs) or its
            ``quantile`` (``location_quantile``).
        location_quantile: The quantile of ``location: quantile``.
        spread: The normal mode's width: ``mad`` (1.4826 median absolute deviation from the
            location) or ``lower_mad`` (the same from the scores below the location only:
            faults sit above the mode and do not widen it).
        k: Spreads above the location at which a logit is a fault.
        window: Number of recent scores the mode is estimated on.
        warmup: Scores seen before the threshold moves (until then: the calibrated one).
        min_spread: Smallest spread in logits (a run of near-identical scores would
            otherwise flag any wiggle).
        floor: Never go below the calibrated threshold (adapt upwards only).
        max_probability: Never go above this calibrated probability (a run of faults must
            not teach the threshold that faults are normal).
    """

    location: Location = "quantile"
    location_quantile: float = Field(default=0.3, gt=0.0, lt=1.0)
    spread: Spread = "lower_mad"
    k: float = Field(default=2.0, gt=0.0, le=50.0)
    window: int = Field(default=200, ge=5, le=100_000)
    warmup: int = Field(default=30, ge=0, le=100_000)
    min_spread: float = Field(default=0.25, gt=0.0, le=10.0)
    floor: bool = True
    max_probability: float = Field(default=0.99, gt=0.0, lt=1.0)


def logit(p: float) -> float:
    """``log(p / (1 - p))`` of ``p`` clipped into ``[1e-12, 1 - 1e-12]``."""
    q = min(max(p, _EPS), 1.0 - _EPS)
    return math.log(q / (1.0 - q))


def half_sample_mode(values: NDArray[np.float64]) -> float:
    """Bickel and Frühwirth's half-sample mode: the shortest half, recursively (O(n log n)).

    Args:
        values: Finite numbers (at least one).

    Returns:
        The mode estimate (the mean of the last two or three values left).
    """
    x = np.sort(values)
    while len(x) > 3:
        h = (len(x) + 1) // 2
        widths = x[h - 1 :] - x[: len(x) - h + 1]
        i = int(np.argmin(widths))
        x = x[i : i + h]
    return float(np.mean(x))


def mode_and_spread(u: NDArray[np.float64], config: AdaptiveConfig) -> tuple[float, float]:
    """Location and spread of the normal mode of logits ``u`` (`AdaptiveConfig`)."""
    if config.location == "median":
        loc = float(np.median(u))
    elif config.location == "quantile":
        loc = float(np.quantile(u, config.location_quantile))
    else:
        loc = half_sample_mode(u)
    dev = u - loc
    if config.spread == "lower_mad":
        dev = dev[dev <= 0.0]
    mad = float(np.median(np.abs(dev))) if len(dev) else 0.0
    return loc, max(MAD_SCALE * mad, config.min_spread)


def _lerp(a: float, b: float, t: float) -> float:
    """The ``_lerp`` of numpy on two floats, operation for operation (bit for bit the same)."""
    d = b - a
    return b - d * (1 - t) if t >= 0.5 else a + d * t


def _quantile_of_sorted(s: list[float], q: float) -> float:
    """``np.quantile(s, q)`` (method ``linear``) of the ascending, finite ``s``, bit for bit."""
    n = len(s)
    v = (n - 1) * q
    if v >= n - 1:  # numpy clamps both neighbours to index -1 and takes gamma against it
        return _lerp(s[-1], s[-1], v + 1)
    lo = math.floor(v)
    return _lerp(s[lo], s[lo + 1], v - lo)


def _median_of(values: list[float]) -> float:
    """``np.median`` of the ascending, finite ``values`` (at least one), bit for bit."""
    n = len(values)
    if n % 2:
        return values[n // 2]
    return (values[n // 2 - 1] + values[n // 2]) / 2.0


def sorted_mode_and_spread(s: list[float], config: AdaptiveConfig) -> tuple[float, float] | None:
    """`mode_and_spread` of the ascending, finite window ``s``, bit for bit, in O(len(s)).

    For the ``quantile`` and ``median`` locations with the ``lower_mad`` spread (the default):
    the logits below the location are a prefix of ``s``, and their distances to it are that
    prefix reversed. None for the other settings (`mode_and_spread` then sorts).
    """
    if config.spread != "lower_mad" or config.location == "half_sample_mode" or not s:
        return None
    if config.location == "quantile":
        loc = _quantile_of_sorted(s, config.location_quantile)
    else:
        loc = _median_of(s)
    m = bisect.bisect_right(s, loc)  # x - loc <= 0 exactly when x <= loc (finite floats)
    dist = [abs(x - loc) for x in reversed(s[:m])]
    mad = _median_of(dist) if dist else 0.0
    return loc, max(MAD_SCALE * mad, config.min_spread)


def sigmoid(u: float) -> float:
    """The logistic function, safe for large ``|u|``."""
    if u >= 0.0:
        return 1.0 / (1.0 + math.exp(-u))
    e = math.exp(u)
    return e / (1.0 + e)


class AdaptiveOperatingPoint:
    """The threshold state alone: scores in, the current logit threshold out (no model).

    Args:
        threshold: The calibrated threshold (probability), used in the warm-up and as the floor.
        config: Settings (None: the defaults).

    Raises:
        ModelError: ``threshold`` is not a probability in (0, 1).
    """

    def __init__(self, threshold: float, config: AdaptiveConfig | None = None) -> None:
        if not 0.0 < float(threshold) < 1.0:
            raise ModelError(f"adaptive operating point: threshold {threshold} is not in (0, 1)")
        self.config = config if config is not None else AdaptiveConfig()
        self.base_threshold = float(threshold)
        self.base_logit = logit(self.base_threshold)
        self._ceiling = logit(self.config.max_probability)
        self._scores: deque[float] = deque(maxlen=self.config.window)
        self._sorted: list[float] = []  # the same scores, ascending (kept by bisection)
        self.n_seen = 0
        self.logit_threshold = self.base_logit
        self.mode = math.nan
        self.spread = math.nan

    @property
    def threshold(self) -> float:
        """The current threshold as a calibrated probability."""
        return sigmoid(self.logit_threshold)

    @property
    def warming_up(self) -> bool:
        """Whether the threshold is still the calibrated one (too few scores seen)."""
        return self.n_seen < max(self.config.warmup, 1)

    def is_fault(self, probability: float) -> bool:
        """Whether ``probability`` is at or above the current threshold (NaN: a fault)."""
        if not math.isfinite(probability):
            return True
        return logit(probability) >= self.logit_threshold

    def observe(self, probability: float) -> None:
        """Add one judged pair's probability to the window and move the threshold.

        A non-finite probability (a broken model) is not a score of the run: it is skipped.
        """
        if not math.isfinite(probability):
            return
        u = logit(float(probability))
        if len(self._scores) == self._scores.maxlen:
            del self._sorted[bisect.bisect_left(self._sorted, self._scores[0])]
        self._scores.append(u)
        bisect.insort(self._sorted, u)
        self.n_seen += 1
        if self.warming_up:
            return
        # the window kept sorted: ~10x cheaper than numpy's quantile and medians on 200
        # values (3 % of a guarded run on Intel), and the same numbers
        fast = sorted_mode_and_spread(self._sorted, self.config)
        if fast is None:
            window = np.fromiter(self._scores, dtype=np.float64, count=len(self._scores))
            fast = mode_and_spread(window, self.config)
        med, spread = fast
        tau = min(med + self.config.k * spread, self._ceiling)
        if self.config.floor:
            tau = max(tau, self.base_logit)
        self.mode, self.spread, self.logit_threshold = med, spread, tau

    def shifted(self, probability: float) -> float:
        """``probability`` moved so that the calibrated threshold decides as the current one."""
        if not math.isfinite(probability) or self.logit_threshold == self.base_logit:
            return probability  # no shift (warm-up, or at the floor): reported as computed
        return sigmoid(logit(probability) - self.logit_threshold + self.base_logit)

    def summary(self) -> dict[str, Any]:
        """Where the operating point stands (for reports)."""
        return {
            "operating_point": "adaptive",
            "calibrated_threshold": self.base_threshold,
            "threshold": self.threshold,
            "n_scores": self.n_seen,
            "warming_up": self.warming_up,
            "normal_mode_logit": self.mode,
            "spread_logit": self.spread,
            **{f"config_{k}": v for k, v in self.config.model_dump().items()},
        }


def replay(
    probabilities: ArrayLike, threshold: float, config: AdaptiveConfig | None = None
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Judge a stream of probabilities in order, as `AdaptiveThreshold` would online.

    Args:
        probabilities: Calibrated fault probabilities in judging order.
        threshold: The calibrated threshold.
        config: Settings (None: the defaults).

    Returns:
        ``(faults, thresholds)``: per score, whether it was called a fault and the threshold
        (probability) it was judged against (the one from the scores before it).
    """
    op = AdaptiveOperatingPoint(threshold, config)
    p = np.asarray(probabilities, dtype=np.float64).reshape(-1)
    faults = np.zeros(len(p), dtype=bool)
    used = np.zeros(len(p), dtype=np.float64)
    for i, v in enumerate(p):
        used[i] = op.threshold
        faults[i] = op.is_fault(float(v))
        op.observe(float(v))
    return faults, used


class AdaptiveThreshold:
    """A detector whose operating point follows this run's normal mode (module docstring).

    Wraps a `scanguard.detect.detector.FaultDetector` (or any detector with ``threshold`` and
    ``fault_probability``); every other attribute is the wrapped detector's. Each probability
    it returns is judged against the threshold of the pairs before it and then learned from,
    so one instance belongs to one run: the pairs must come in the order they are judged.

    Args:
        detector: The detector.
        config: Settings (None: the defaults).
        threshold: The calibrated threshold to start from and decide with (None: the
            detector's own).

    Raises:
        ModelError: The threshold is not in (0, 1).
    """

    def __init__(
        self, detector: Any, config: AdaptiveConfig | None = None, threshold: float | None = None
    ) -> None:
        self.detector = detector
        base = float(detector.threshold if threshold is None else threshold)
        self.operating_point = AdaptiveOperatingPoint(base, config)
        logger.debug(
            "adaptive operating point on %s (calibrated threshold %.3g)",
            getattr(detector, "source", type(detector).__name__),
            self.operating_point.base_threshold,
        )

    def __getattr__(self, name: str) -> Any:
        # only called for attributes not found here: the wrapped detector's (style, source,
        # metric_names, match_features, ...), so the judge renders and reads as for it
        if name == "detector":  # not set yet (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.detector, name)

    @property
    def threshold(self) -> float:
        """The calibrated threshold: the returned probabilities are shifted to meet it."""
        return self.operating_point.base_threshold

    @property
    def current_threshold(self) -> float:
        """The adaptive threshold now, as a calibrated probability of the wrapped detector."""
        return self.operating_point.threshold

    def _judged(self, probability: float) -> float:
        """Shift by the threshold of the past, then learn from this pair."""
        out = self.operating_point.shifted(probability)
        self.operating_point.observe(probability)
        return out

    def predict_images(self, images: NDArray[np.uint8], *args: Any, **kwargs: Any) -> Any:
        """The wrapped detector's `predict_images`, each pair shifted then learned, in order."""
        raw = np.asarray(self.detector.predict_images(images, *args, **kwargs), dtype=np.float64)
        return np.array([self._judged(float(p)) for p in raw.reshape(-1)], dtype=np.float64)

    def fault_probability(self, *args: Any, **kwargs: Any) -> float:
        """The wrapped detector's `fault_probability`, shifted, then learned from."""
        return self._judged(float(self.detector.fault_probability(*args, **kwargs)))

    def summary(self) -> dict[str, Any]:
        """Where the operating point stands (`AdaptiveOperatingPoint.summary`)."""
        return self.operating_point.summary()

    def __repr__(self) -> str:
        return f"AdaptiveThreshold({self.detector!r}, {self.operating_point.config!r})"


def calibrated_detector(detector: Any) -> Any:
    """The detector an `AdaptiveThreshold` wraps (any other detector as it is)."""
    return detector.detector if isinstance(detector, AdaptiveThreshold) else detector


def with_operating_point(
    detector: Any,
    mode: OperatingPoint,
    config: AdaptiveConfig | None = None,
    threshold: float | None = None,
) -> Any:
    """``detector`` itself (``fixed``) or wrapped in an `AdaptiveThreshold` (``adaptive``).

    ``threshold``: the one to start from (None: the detector's). A threshold not strictly
    inside (0, 1) cannot adapt: the detector is returned as it is, with a warning.
    """
    if mode == "fixed" or detector is None:
        return detector
    t = float(getattr(detector, "threshold", math.nan) if threshold is None else threshold)
    if not 0.0 < t < 1.0:
        logger.warning("threshold %s cannot adapt (not in (0, 1)): the fixed one is used", t)
        return detector
    return AdaptiveThreshold(detector, config, t)
