"""The features of one matched pair, assembled once for the dataset, the detector and the guard.

A pair's features are the match's quality metrics (``MatchResult.metrics()``), optionally
GMapping's likelihood score of the pair (`scanguard.matching.quality.gmapping_score`, the raw
sum: ``gmapping_score_norm`` is derived by the detectors), optionally the per-beam residual
profile (`scanguard.pairs.profile`) and optionally the odometry disagreement
(`scanguard.pairs.odometry`). The dataset stores exactly these columns, so a detector sees at
run time what it was trained on.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.matching.quality import gmapping_score
from scanguard.pairs.odometry import OdometryNoise, odometry_disagreement
from scanguard.pairs.profile import PROFILE_FEATURES, residual_profile
from scanguard.scan import LaserScan

Points = LaserScan | NDArray[np.floating[Any]]


def pair_metrics(
    previous: Points, current: Points, match: Any, *, gmapping: bool
) -> dict[str, Any]:
    """Quality metrics of one match, plus ``gmapping_score`` when asked.

    Args:
        previous: Previous scan (the match's target) or its ``(N, 2)`` points.
        current: Current scan (the match's source) or its points.
        match: A `scanguard.matching.MatchResult` (anything with ``pose`` and ``metrics()``; a
            match without ``metrics()`` contributes no metric).
        gmapping: Also score the pair with `gmapping_score` (it costs about as much as the ICP).

    Returns:
        ``{name: value}`` in the order ``metrics()`` gives them, ``gmapping_score`` last.
    """
    metrics = getattr(match, "metrics", None)
    feats: dict[str, Any] = dict(metrics()) if callable(metrics) else {}
    if gmapping:
        pose = np.asarray(match.pose, dtype=np.float64)
        feats["gmapping_score"] = float(gmapping_score(previous, current, pose))
    return feats


def pair_features(
    previous: Points,
    current: Points,
    match: Any,
    *,
    gmapping: bool = False,
    profile: bool = False,
    odometry: ArrayLike | None = None,
    noise: OdometryNoise | None = None,
    with_odometry: bool = False,
) -> dict[str, NDArray[np.float64]]:
    """Feature columns (length 1) of one matched pair, as the detectors read them.

    Args:
        previous: Previous scan or its ``(N, 2)`` points.
        current: Current scan or its points.
        match: The match (``pose`` and ``metrics()``).
        gmapping: Add ``gmapping_score`` (`pair_metrics`).
        profile: Add the per-beam residual profile (``PROFILE_FEATURES``).
        odometry: The pair's odometry increment ``(3,)`` in the sensor frame (the estimate's
            convention); ``None``: this pair has no odometry (the mask column says so).
        noise: Odometry noise model of the disagreement (default `OdometryNoise()`).
        with_odometry: Add the odometry disagreement columns (``ODOMETRY_FEATURES``).

    Returns:
        ``{name: (1,) float64 array}``.
    """
    feats = pair_metrics(previous, current, match, gmapping=gmapping)
    out = {k: np.array([v], dtype=np.float64) for k, v in feats.items()}
    if profile:
        prof = residual_profile(_points(previous), _points(current), match.pose)
        out.update({n: np.array([v]) for n, v in zip(PROFILE_FEATURES, prof, strict=True)})
    if with_odometry:
        out.update(
            odometry_disagreement(
                np.asarray(match.pose, dtype=np.float64).reshape(1, 3),
                None if odometry is None else np.asarray(odometry, np.float64).reshape(1, 3),
                noise,
            )
        )
    return out


def _points(scan: Points) -> NDArray[np.float64]:
    if isinstance(scan, LaserScan):
        return np.asarray(scan.points(np.float64))
    return np.asarray(scan, dtype=np.float64)
