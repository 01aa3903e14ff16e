"""Calibrating a detector on labelled pairs it was not trained on, and saving the result.

`calibrate_detector` computes the detector's fault logits on a pair store (or takes them as
arrays) and fits a `scanguard.detect.calibrate.Calibration`; `save_calibrated` writes a
checkpoint with the calibration block added. The calibration maths is
`scanguard.detect.calibrate`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from scanguard.dataset.store import PairStore
from scanguard.detect.calibrate import (
    Calibration,
    CalibrationFit,
    Method,
    ThresholdRule,
    check_calibration_fit,
    check_calibration_pairs,
    fit_calibration,
)
from scanguard.detect.checkpoint import load_checkpoint, with_calibration
from scanguard.detect.detector import FaultDetector, default_model_path
from scanguard.detect.features import store_features
from scanguard.detect.images import render_all
from scanguard.errors import ConfigError
from scanguard.fsutil import atomic_path
from scanguard.scoring import sigmoid


def store_logits(
    detector: FaultDetector, store: Any, splits: Sequence[str] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], str]:
    """Labels, fault logit margins and current probabilities of a pair store's pairs.

    Args:
        detector: The detector.
        store: Pair store (folder, ``.h5`` file(s), or an open `PairStore`).
        splits: Splits to use (``None``: all pairs).

    Returns:
        ``(labels, logits, probabilities, description of the store)``.

    Raises:
        ConfigError: No pairs.
    """
    ps = store if isinstance(store, PairStore) else PairStore.open(store)
    idx = ps.indices(None if splits is None else list(splits), include_ambiguous=True)
    if len(idx) == 0:
        raise ConfigError(f"calibration: no pairs in split(s) {splits}")
    labels = np.asarray(ps.records["label"], dtype=np.int64)[idx]
    images = render_all(ps, idx, detector.style, progress=False)
    feats = (
        store_features(ps, idx, detector.odometry_noise, detector.reads_profile)
        if detector.metric_names
        else None
    )
    logits = detector.predict_logits(images, features=feats)
    proba = detector.predict_images(images, features=feats)
    files = [Path(str(f)).name for f in getattr(ps, "files", [])]
    where = ", ".join(files[:3]) + (", ..." if len(files) > 3 else "")
    return labels, logits, proba, where


def decision_logit(detector: FaultDetector) -> float:
    """The fault logit at which ``detector``'s probability equals its threshold."""
    t = min(max(float(detector.threshold), 1e-12), 1.0 - 1e-12)
    a, b = detector.calibration.slope_offset if detector.calibration is not None else (1.0, 0.0)
    return (math.log(t / (1.0 - t)) - b) / a


def calibrate_detector(
    detector: FaultDetector,
    store_or_pairs: Any,
    *,
    method: Method = "temperature",
    splits: Sequence[str] | None = None,
    fitted_on: str | None = None,
    threshold_rule: ThresholdRule = "balanced_accuracy",
) -> CalibrationFit:
    """Fit a calibration of ``detector`` on labelled pairs it was not trained on.

    Args:
        detector: The detector (its current calibration, if any, is the "before"; the new
            one is fitted on its raw logits and replaces it).
        store_or_pairs: A pair store (folder, ``.h5`` file(s), open `PairStore`), or
            ``(labels, logits)`` arrays.
        method: ``"temperature"`` or ``"platt"``.
        splits: Splits of the store to use (``None``: all).
        fitted_on: Description stored in the block (default: the store's files).
        threshold_rule: ``balanced_accuracy`` (the project rule, on these pairs) or ``keep``
            (the detector's decision boundary: only the probabilities change).

    Returns:
        The fit; ``fit.calibration`` is the block `with_calibration` adds to a checkpoint.

    Raises:
        ConfigError: Too few pairs of a class (`check_calibration_pairs`), or a fit that ran
            to its bound (`check_calibration_fit`).
    """
    if isinstance(store_or_pairs, tuple) and len(store_or_pairs) == 2:
        labels, logits = (np.asarray(a) for a in store_or_pairs)
        cal = detector.calibration
        proba = cal.apply(logits) if cal is not None else sigmoid(logits)
        where = "arrays"
    else:
        labels, logits, proba, where = store_logits(detector, store_or_pairs, splits)
    # a model written from one class or a pair or two would claim a certainty nobody measured
    source = where if fitted_on is None else fitted_on
    check_calibration_pairs(labels, logits, source)
    fit = fit_calibration(
        labels,
        logits,
        method=method,
        proba_before=proba,
        threshold_before=detector.threshold,
        fitted_on=source,
        keep_logit=decision_logit(detector) if threshold_rule == "keep" else None,
    )
    check_calibration_fit(fit, source)
    return fit


def save_calibrated(
    model: str | Path | None,
    calibration: Calibration,
    out: str | Path,
    *,
    overwrite_input: bool = False,
) -> Path:
    """Write ``model`` (None: the shipped one) plus ``calibration`` to ``out``, atomically.

    Raises:
        ConfigError: ``out`` is the input file and ``overwrite_input`` is not set.
        ModelError: The input is not a readable checkpoint.
    """
    src = default_model_path() if model is None else Path(model)
    if src.is_dir():
        src = src / "model.pt"
    dest = Path(out)
    if dest.exists() and dest.resolve() == src.resolve() and not overwrite_input:
        raise ConfigError(f"{dest}: refusing to overwrite the input model (write elsewhere)")
    ckpt = with_calibration(load_checkpoint(src), calibration)
    with atomic_path(dest) as tmp:
        torch.save(ckpt, tmp)
    return dest
