"""Feature columns the detectors read: derived metrics and a pair store's feature table.

The dataset stores the raw quality metrics of each match (``MatchResult.metrics()`` plus the
raw ``gmapping_score``); `with_derived_features` adds the scale-free ratios every detector
reads, and `store_features` assembles the full table of a pair store (metrics, derived
ratios, odometry disagreement and, when asked, the residual profile). This module sits at the
bottom of `scanguard.detect`: the model, the classical baselines, training, evaluation and
calibration all read features through it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.pairs.odometry import odometry_disagreement
from scanguard.pairs.profile import store_profiles

FloatArray = NDArray[np.float64]


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


def store_features(
    store: Any, idx: NDArray[np.int64], odometry_noise: Any = None, profile: bool = False
) -> dict[str, NDArray[np.float64]]:
    """ICP quality metrics (plus derived ones) and odometry features of pairs of a store.

    Args:
        store: A `scanguard.dataset.PairStore`.
        idx: Record indices.
        odometry_noise: `scanguard.pairs.odometry.OdometryNoise` of the odometry features
            (default: the default model; a detector passes its own).
        profile: Also compute the per-beam residual profile (`scanguard.pairs.profile`; a
            nearest-neighbour query per pair, so only when a model reads it).

    Returns:
        Columns by name: the store's metrics, `with_derived_features`, and the
        `scanguard.pairs.odometry.ODOMETRY_FEATURES` (masked where a pair has no odometry).
    """
    rec = store.records
    # a metric listed by the store can still be missing from its records; use what is there
    names = [k for k in dict.fromkeys([*store.metric_names, "iterations", "converged"]) if k in rec]
    feats = with_derived_features({k: np.asarray(rec[k])[idx] for k in names})
    odo = rec.get("odometry_increment")
    feats.update(
        odometry_disagreement(
            np.asarray(rec["estimate"])[idx],
            None if odo is None else np.asarray(odo)[idx],
            odometry_noise,
        )
    )
    if profile:
        feats.update(store_profiles(store, idx))
    return feats
