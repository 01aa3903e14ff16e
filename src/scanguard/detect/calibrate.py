"""Calibration of the fault probability and the operating threshold shipped with a model.

A trained CNN ranks pairs well on data it never saw, but its probabilities and the threshold
chosen on the validation split of its own training environments do not transfer. This module
refits both on labelled pairs the model was not trained on (a held-out environment, or one
recording of the user's robot with a reference):

* **Temperature scaling** (``method="temperature"``): ``p = sigmoid(z / T)`` with ``z`` the
  fault logit margin (``logit_fault - logit_normal``; the uncalibrated probability is
  ``sigmoid(z)``) and one scalar ``T > 0``. It keeps the ranking.
* **Platt scaling** (``method="platt"``): ``p = sigmoid(a * z + b)`` with ``a > 0``. It keeps
  the ranking and can also shift the decision point.

Both minimise the negative log-likelihood (binary cross entropy) of the labelled pairs with
`scipy.optimize`; ambiguous pairs (label -1) are excluded.

**Threshold rule** (`choose_threshold`): the operating threshold on the calibrated
probability maximises the **balanced accuracy** (mean of the recall of faults and the recall
of normal matches) on the calibration pairs. Candidates are 0.5 and the midpoints between
consecutive distinct calibrated probabilities; scores equal to within ``1e-12`` are ties, and
ties go to the candidate closest to 0.5. With only one class present the threshold is 0.5.
A pair is a fault when ``p >= threshold``.

**Expected calibration error** (`expected_calibration_error`): 15 equal-width bins of the
predicted fault probability on ``[0, 1]`` (bin ``k`` is ``[k/15, (k+1)/15)``, the last one
includes 1); ECE is the mean over bins, weighted by the bin counts, of ``|mean predicted fault
probability - observed fault frequency|``. The reliability diagram (`plot_reliability`) shows
the observed fault frequency per bin against the mean predicted probability, with counts.

A calibrated checkpoint is the original checkpoint plus a ``calibration`` block
(`Calibration.to_dict`, added by `scanguard.detect.checkpoint.with_calibration`);
`scanguard.detect.detector.FaultDetector` applies it and uses its threshold. A checkpoint
without the block behaves exactly as before. Fitting a detector's calibration on a pair store
and writing the calibrated checkpoint is `scanguard.detect.recalibrate`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import ConfigError, ModelError
from scanguard.fsutil import save_figure
from scanguard.scoring import (
    ECE_BINS,
    balanced_accuracy,
    choose_threshold,
    confusion,
    expected_calibration_error,
    reliability,
    sigmoid,
)
from scanguard.scoring import labelled as _labelled

log = logging.getLogger(__name__)

Method = Literal["temperature", "platt"]
METHODS: tuple[str, ...] = ("temperature", "platt")
ThresholdRule = Literal["balanced_accuracy", "keep"]
#: How a calibration picks its threshold: the project rule (maximum balanced accuracy on the
#: calibration pairs, ties -> 0.5), or ``keep``: the decision boundary the model had (the same
#: fault logit), so that only the probabilities change, never a verdict.
THRESHOLD_RULES: tuple[str, ...] = ("balanced_accuracy", "keep")


def _log_sigmoid(z: NDArray[np.float64]) -> NDArray[np.float64]:
    return -np.logaddexp(0.0, -z)


@dataclass(frozen=True)
class Calibration:
    """A fitted calibration, as stored in a checkpoint's ``calibration`` block.

    Attributes:
        method: ``"temperature"`` or ``"platt"``.
        threshold: Operating threshold on the calibrated probability.
        temperature: ``T`` of temperature scaling (``p = sigmoid(z / T)``).
        a: Slope of Platt scaling (``p = sigmoid(a * z + b)``).
        b: Offset of Platt scaling.
        fitted_on: Where the calibration pairs came from.
        n_pairs: Labelled pairs it was fitted on.
        ece_before: ECE of the probabilities before calibration.
        ece_after: ECE after calibration.
        balanced_accuracy_before: At the previous threshold, before calibration.
        balanced_accuracy_after: At ``threshold``, after calibration.
    """

    method: Method
    threshold: float
    temperature: float | None = None
    a: float | None = None
    b: float | None = None
    fitted_on: str = ""
    n_pairs: int = 0
    ece_before: float = math.nan
    ece_after: float = math.nan
    balanced_accuracy_before: float = math.nan
    balanced_accuracy_after: float = math.nan
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def slope_offset(self) -> tuple[float, float]:
        """``(a, b)`` such that ``p = sigmoid(a * z + b)`` for either method."""
        if self.method == "temperature":
            return 1.0 / float(self.temperature or 1.0), 0.0
        return float(self.a if self.a is not None else 1.0), float(self.b or 0.0)

    def apply(self, logits: ArrayLike) -> NDArray[np.float64]:
        """Calibrated fault probabilities of fault logit margins ``z``."""
        z = np.asarray(logits, dtype=np.float64)
        if self.method == "temperature":
            return sigmoid(z / float(self.temperature or 1.0))
        a, b = self.slope_offset
        return sigmoid(a * z + b)

    def to_dict(self) -> dict[str, Any]:
        """The checkpoint block (plain JSON types; NaN written as None)."""

        def clean(v: Any) -> Any:
            return None if isinstance(v, float) and not math.isfinite(v) else v

        out: dict[str, Any] = {"method": self.method}
        if self.method == "temperature":
            out["temperature"] = float(self.temperature or 1.0)
        else:
            out["a"], out["b"] = self.slope_offset
        out.update(
            threshold=float(self.threshold),
            fitted_on=str(self.fitted_on),
            n_pairs=int(self.n_pairs),
            ece_before=clean(float(self.ece_before)),
            ece_after=clean(float(self.ece_after)),
            balanced_accuracy_before=clean(float(self.balanced_accuracy_before)),
            balanced_accuracy_after=clean(float(self.balanced_accuracy_after)),
        )
        if self.extra:
            out["extra"] = dict(self.extra)
        return out

    @classmethod
    def from_dict(cls, block: Any, source: str | Path = "<checkpoint>") -> Calibration:
        """Read and check a checkpoint's ``calibration`` block.

        Raises:
            ModelError: Not a mapping, unknown method, or a parameter or threshold that is
                missing, not finite or out of range; the message names ``source``.
        """
        if not isinstance(block, Mapping):
            raise ModelError(f"{source}: calibration block is not a mapping")
        method = block.get("method")
        if method not in METHODS:
            raise ModelError(
                f"{source}: unknown calibration method {method!r} ({' or '.join(METHODS)})"
            )

        def number(key: str, positive: bool = False) -> float:
            try:
                v = float(block[key])
            except KeyError:
                raise ModelError(f"{source}: {method} calibration lacks {key!r}") from None
            except (TypeError, ValueError):
                raise ModelError(
                    f"{source}: calibration {key} {block[key]!r} is not a number"
                ) from None
            if not math.isfinite(v) or (positive and v <= 0):
                need = "a finite number > 0" if positive else "a finite number"
                raise ModelError(f"{source}: calibration {key} {v} is not {need}")
            return v

        def optional(key: str) -> float:
            v = block.get(key)
            try:
                return math.nan if v is None else float(v)
            except (TypeError, ValueError):
                return math.nan

        threshold = number("threshold")
        if not 0.0 <= threshold <= 1.0:
            raise ModelError(
                f"{source}: calibration threshold {threshold} is not a probability in [0, 1]"
            )
        params: dict[str, float | None] = {}
        if method == "temperature":
            params["temperature"] = number("temperature", positive=True)
        else:
            params["a"] = number("a", positive=True)
            params["b"] = number("b")
        n = block.get("n_pairs", 0)
        return cls(
            method=method,
            threshold=threshold,
            fitted_on=str(block.get("fitted_on", "")),
            n_pairs=int(n) if isinstance(n, int | float) and math.isfinite(n) else 0,
            ece_before=optional("ece_before"),
            ece_after=optional("ece_after"),
            balanced_accuracy_before=optional("balanced_accuracy_before"),
            balanced_accuracy_after=optional("balanced_accuracy_after"),
            extra=dict(block.get("extra") or {}),
            **params,
        )


def fit_temperature(labels: ArrayLike, logits: ArrayLike) -> float:
    """Temperature ``T`` minimising the NLL of ``sigmoid(z / T)`` on labelled pairs.

    Args:
        labels: 0 (normal) / 1 (fault); other values (ambiguous) are ignored.
        logits: Fault logit margins ``z``.

    Returns:
        ``T`` in ``[1e-3, 1e3]``.

    Raises:
        ConfigError: No labelled pair with a finite logit.
    """
    from scipy.optimize import minimize_scalar

    y, z = _labelled(labels, logits, "fit_temperature")
    if y.size == 0:
        raise ConfigError("calibration: no labelled pairs (normal or fault) to fit on")
    sign = 2.0 * y - 1.0  # NLL = -log sigmoid(sign * z / T)

    def nll(log_t: float) -> float:
        return float(-np.mean(_log_sigmoid(sign * z * math.exp(-log_t))))

    lo, hi = TEMPERATURE_BOUNDS
    res = minimize_scalar(
        nll, bounds=(math.log(lo), math.log(hi)), method="bounded", options={"xatol": 1e-7}
    )
    return float(math.exp(float(res.x)))


def fit_platt(labels: ArrayLike, logits: ArrayLike) -> tuple[float, float]:
    """Platt parameters ``(a, b)``, ``a > 0``, minimising the NLL of ``sigmoid(a z + b)``.

    Raises:
        ConfigError: No labelled pair with a finite logit.
    """
    from scipy.optimize import minimize

    y, z = _labelled(labels, logits, "fit_platt")
    if y.size == 0:
        raise ConfigError("calibration: no labelled pairs (normal or fault) to fit on")
    sign = 2.0 * y - 1.0

    def nll(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        u = sign * (theta[0] * z + theta[1])
        loss = float(-np.mean(_log_sigmoid(u)))
        g = -sign * sigmoid(-u)  # d loss_i / d (a z + b)
        return loss, np.array([np.mean(g * z), np.mean(g)])

    res = minimize(
        nll,
        np.array([1.0, 0.0]),
        jac=True,
        method="L-BFGS-B",
        bounds=[(1e-6, None), (None, None)],
    )
    return float(res.x[0]), float(res.x[1])


def plot_reliability(
    panels: Sequence[tuple[str, ArrayLike, ArrayLike]],
    path: str | Path,
    bins: int = ECE_BINS,
    title: str = "",
) -> Path:
    """Reliability diagrams as PNG: observed fault frequency vs mean predicted probability.

    Args:
        panels: ``(title, labels, fault probabilities)`` per panel.
        path: Destination PNG (written atomically).
        bins: Equal-width bins.
        title: Figure title.

    Returns:
        The path written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncol = max(1, min(3, len(panels)))
    nrow = max(1, math.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 4.2 * nrow), squeeze=False)
    for k, (name, labels, proba) in enumerate(panels):
        ax = axes[k // ncol][k % ncol]
        r = reliability(labels, proba, bins)
        centers = (r.edges[:-1] + r.edges[1:]) / 2
        width = 1.0 / bins
        filled = r.count > 0
        ax.bar(
            centers[filled],
            r.frequency[filled],
            width=width * 0.9,
            color="tab:blue",
            alpha=0.7,
            label="observed fault frequency",
        )
        ax.plot(r.confidence[filled], r.frequency[filled], "o", color="tab:red", ms=3)
        ax.plot([0, 1], [0, 1], "k:", lw=0.8, label="perfect calibration")
        for c, f, n in zip(centers[filled], r.frequency[filled], r.count[filled], strict=True):
            ax.text(c, min(float(f) + 0.02, 0.97), str(int(n)), ha="center", fontsize=6)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_xlabel("predicted fault probability")
        ax.set_ylabel("observed fault frequency")
        ece = "-" if not math.isfinite(r.ece) else f"{r.ece:.3f}"
        ax.set_title(f"{name} (ECE {ece}, n {int(r.count.sum())})", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    for k in range(len(panels), nrow * ncol):
        axes[k // ncol][k % ncol].axis("off")
    if title:
        fig.suptitle(title)
    p = save_figure(fig, Path(path), dpi=100)
    return p


@dataclass
class CalibrationFit:
    """What `fit_calibration` (and `scanguard.detect.recalibrate.calibrate_detector`) return.

    Attributes:
        calibration: The fitted `Calibration` (the checkpoint block).
        labels: Labels of the calibration pairs (ambiguous included, as -1).
        logits: Their fault logit margins.
        proba_before: Probabilities before (the detector as it was).
        proba_after: Calibrated probabilities.
        threshold_before: The threshold before.
    """

    calibration: Calibration
    labels: NDArray[np.int64]
    logits: NDArray[np.float64]
    proba_before: NDArray[np.float64]
    proba_after: NDArray[np.float64]
    threshold_before: float

    def report(self) -> dict[str, Any]:
        """JSON-compatible summary (calibration, counts, metrics before and after)."""
        y = self.labels
        cal = self.calibration
        return {
            "calibration": cal.to_dict(),
            "pairs": {
                "normal": int(np.sum(y == 0)),
                "fault": int(np.sum(y == 1)),
                "ambiguous": int(np.sum(y == -1)),
            },
            "before": _metrics(y, self.proba_before, self.threshold_before),
            "after": _metrics(y, self.proba_after, cal.threshold),
        }


def _metrics(labels: NDArray[np.int64], proba: NDArray[np.float64], t: float) -> dict[str, Any]:
    row = confusion(labels, proba, t)
    row["balanced_accuracy"] = balanced_accuracy(labels, proba, t)
    row["ece"] = expected_calibration_error(labels, proba)
    return {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()
    }


#: Fewest pairs of each class (normal, fault) the ``calibrate`` command fits on: with one
#: class only, or a pair or two, the fit runs to the optimiser's bound (temperature 1e-3 or
#: 1e3) and the model it writes claims a certainty nothing measured.
MIN_PAIRS_PER_CLASS = 3
#: The temperature bounds of `fit_temperature`.
TEMPERATURE_BOUNDS = (1e-3, 1e3)


def check_calibration_pairs(labels: ArrayLike, logits: ArrayLike, where: str) -> None:
    """Refuse labelled pairs that cannot determine a calibration.

    Raises:
        ConfigError: Fewer than `MIN_PAIRS_PER_CLASS` labelled pairs of either class (with a
            finite logit); names ``where`` and the counts.
    """
    y, _z = _labelled(labels, logits, "calibration")
    n_fault = int(y.sum())
    n_normal = int(y.size) - n_fault
    if min(n_normal, n_fault) < MIN_PAIRS_PER_CLASS:
        raise ConfigError(
            f"{where}: {n_normal} normal and {n_fault} fault pair(s): a calibration needs at "
            f"least {MIN_PAIRS_PER_CLASS} of each class (one class or a few pairs determine "
            "no temperature); give more labelled pairs"
        )


def check_calibration_fit(fit: CalibrationFit, where: str) -> None:
    """Refuse a fit that the pairs do not determine.

    Two signs: the temperature ran to `TEMPERATURE_BOUNDS` (classes not separated at all:
    every probability 0.5), or every labelled pair's calibrated probability is saturated
    (within 1e-6 of 0 or 1: classes perfectly separated, the NLL flat in ``T``, which stops
    anywhere near 0, e.g. at 0.0035); Platt's slope at its lower bound likewise.

    Raises:
        ConfigError: The fit is degenerate; names ``where``.
    """
    cal = fit.calibration
    lo, hi = TEMPERATURE_BOUNDS
    t, a = cal.temperature, cal.a
    keep = (fit.labels == 0) | (fit.labels == 1)
    p = fit.proba_after[keep]
    saturated = bool(p.size) and bool(np.all((p < 1e-6) | (p > 1.0 - 1e-6)))
    at_bound = (t is not None and not lo * 1.01 < t < hi / 1.01) or (a is not None and a <= 1e-5)
    if saturated or at_bound:
        value = f"temperature {t:.4g}" if t is not None else f"slope {a:.3g}"
        why = "perfectly separated" if saturated else "not separated at all"
        raise ConfigError(
            f"{where}: the fit is degenerate ({value}; the classes are {why}): these pairs "
            "determine no calibration; give more, varied labelled pairs"
        )


def fit_calibration(
    labels: ArrayLike,
    logits: ArrayLike,
    *,
    method: Method = "temperature",
    proba_before: ArrayLike | None = None,
    threshold_before: float = 0.5,
    fitted_on: str = "",
    keep_logit: float | None = None,
) -> CalibrationFit:
    """Fit a calibration and choose its threshold from labelled logits.

    Args:
        labels: 0 / 1 / -1 (ambiguous, excluded from the fit) per pair.
        logits: Fault logit margins ``z`` per pair.
        method: ``"temperature"`` or ``"platt"``.
        proba_before: The probabilities in use before (default ``sigmoid(z)``).
        threshold_before: The threshold in use before.
        fitted_on: Description stored in the block.
        keep_logit: The threshold rule ``keep``: the fault logit of the decision boundary in
            use before; the new threshold is the new probability there, so every verdict
            stays as it was. None: the project rule (`choose_threshold`).

    Raises:
        ConfigError: Unknown method, no labelled pairs, or a ``keep_logit`` that is not
            finite.
    """
    if method not in METHODS:
        raise ConfigError(f"calibration method must be {' or '.join(METHODS)}, got {method!r}")
    if keep_logit is not None and not math.isfinite(keep_logit):
        raise ConfigError(f"calibration: the decision boundary to keep is {keep_logit}")
    y = np.asarray(labels, dtype=np.int64).reshape(-1)
    z = np.asarray(logits, dtype=np.float64).reshape(-1)
    before = sigmoid(z) if proba_before is None else np.asarray(proba_before, np.float64)
    yl, _ = _labelled(y, z, "calibration")
    if yl.size == 0:
        raise ConfigError("calibration: no labelled pairs (normal or fault) to fit on")
    if yl.all() or not yl.any():
        log.warning(
            "calibration pairs hold only %s; the threshold stays 0.5",
            "faults" if yl.any() else "normal matches",
        )
    if method == "temperature":
        t = fit_temperature(y, z)
        params: dict[str, Any] = {"temperature": t}
        after = sigmoid(z / t)
    else:
        a, b = fit_platt(y, z)
        params = {"a": a, "b": b}
        after = sigmoid(a * z + b)
    if keep_logit is None:
        threshold, rule = choose_threshold(y, after), "balanced_accuracy"
    else:
        a_new, b_new = (1.0 / params["temperature"], 0.0) if method == "temperature" else (a, b)
        threshold, rule = float(sigmoid(np.array(a_new * keep_logit + b_new))), "keep"
    cal = Calibration(
        method=method,
        threshold=threshold,
        fitted_on=fitted_on,
        n_pairs=int(yl.size),
        ece_before=expected_calibration_error(y, before),
        ece_after=expected_calibration_error(y, after),
        balanced_accuracy_before=balanced_accuracy(y, before, threshold_before),
        balanced_accuracy_after=balanced_accuracy(y, after, threshold),
        # only the rule that is not the project's is recorded (older blocks carry none)
        extra={"threshold_rule": rule} if rule != "balanced_accuracy" else {},
        **params,
    )
    log.info(
        "calibration (%s) on %d pairs: %s, threshold %.3f, ECE %.4f -> %.4f",
        method,
        cal.n_pairs,
        ", ".join(f"{k} {v:.4f}" for k, v in params.items()),
        threshold,
        cal.ece_before,
        cal.ece_after,
    )
    return CalibrationFit(cal, y, z, before, after, float(threshold_before))
