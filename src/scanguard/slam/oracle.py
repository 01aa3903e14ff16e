"""Reference labels of scan matches: what the ``oracle`` gate and the gate-quality tables read.

The rule is the one the training data was labelled with (`scanguard.pairs.labels`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import InputError
from scanguard.geometry import compose, relative
from scanguard.pairs.labels import FAULT, LabelConfig, assign_labels, pair_errors
from scanguard.scan import ScanSequence


def reference_labels(
    seq: ScanSequence, estimates: NDArray[np.float64], labels: LabelConfig
) -> NDArray[np.int8]:
    """Labels of all consecutive pair matches against the reference (NaN estimates = faults)."""
    if seq.reference is None:
        raise InputError(None, f"sequence {seq.name!r} has no reference: cannot label")
    sensor = compose(np.asarray(seq.reference, dtype=np.float64), seq.laser_offset)
    ref_rel = relative(sensor[:-1], sensor[1:])
    errs = np.full((len(estimates), 3), np.nan)
    for k, est in enumerate(estimates):
        if np.all(np.isfinite(est)):
            errs[k] = pair_errors(est, ref_rel[k], seq.scans[k + 1].points(np.float64))
    diverged = ~np.all(np.isfinite(np.asarray(estimates, dtype=np.float64)), axis=1)
    return assign_labels(errs[:, 0], errs[:, 1], errs[:, 2], labels, diverged=diverged)


def pair_label(
    estimate: NDArray[np.float64] | None,
    reference: NDArray[np.float64],
    points: NDArray[np.floating[Any]],
    labels: LabelConfig,
) -> int:
    """Reference label of one match (`reference_labels` for a single pair; None = fault)."""
    if estimate is None or not np.all(np.isfinite(estimate)):
        return FAULT
    t, r, d = pair_errors(estimate, reference, points)
    return int(assign_labels(np.array([t]), np.array([r]), np.array([d]), labels)[0])
