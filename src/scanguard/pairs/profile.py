"""A per-beam residual profile of a matched pair: where along the scan the match fails.

After alignment every current point has a residual, its distance to the nearest previous
point. The profile keeps them in beam order and summarises them in `PROFILE_BINS` equal
segments of the current scan's valid beams (so the same number of inputs for any beam count
or field of view): per segment the median residual, as ``log10(max(d, 1 mm))`` of distances
clipped at `PROFILE_CLIP` (a point with no counterpart within reach is simply "far").

A moving person spoils a few neighbouring segments; a wrong match lifts most of them; a
corridor slide lifts none (which is why the odometry input exists). The profile enters a
hybrid model like the ICP metrics (`scanguard.detect.model.PROFILE_FEATURES`).
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.geometry import transform_points

__all__ = ["PROFILE_BINS", "PROFILE_CLIP", "PROFILE_FEATURES", "residual_profile"]

#: Segments of the profile.
PROFILE_BINS = 16
#: Residuals beyond this (m) count as this: no counterpart within reach.
PROFILE_CLIP = 2.0
#: Feature names of the profile, segment 0 first (first valid beam).
PROFILE_FEATURES: tuple[str, ...] = tuple(f"residual_profile_{k:02d}" for k in range(PROFILE_BINS))
# log10 floor: 1 mm, below any range noise
_FLOOR = 1e-3


def residual_profile(
    previous: ArrayLike, current: ArrayLike, pose: ArrayLike, bins: int = PROFILE_BINS
) -> NDArray[np.float64]:
    """The profile ``(bins,)`` of one pair.

    Args:
        previous: Previous scan's valid points ``(N, 2)`` (its sensor frame).
        current: Current scan's valid points ``(M, 2)`` in beam order (its sensor frame).
        pose: Match estimate: the current sensor frame in the previous one.
        bins: Number of segments.

    Returns:
        ``log10`` of the per-segment median residual (clipped to ``[1 mm, PROFILE_CLIP]``); a
        segment without points (fewer points than segments) repeats the scan's median; a pair
        without points in either scan, or a non-finite pose, is all ``log10(PROFILE_CLIP)``.
    """
    prev = np.asarray(previous, dtype=np.float64).reshape(-1, 2)
    cur = np.asarray(current, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(pose, dtype=np.float64).reshape(3)
    far = np.full(bins, np.log10(PROFILE_CLIP))
    if len(prev) == 0 or len(cur) == 0 or not np.all(np.isfinite(p)):
        return far
    # imported here: every run imports this module for its feature names, few compute it,
    # and scipy.spatial costs a run's start ~0.3 s
    from scipy.spatial import cKDTree

    d, _ = cKDTree(prev).query(transform_points(p, cur), distance_upper_bound=PROFILE_CLIP)
    d = np.clip(np.where(np.isfinite(d), d, PROFILE_CLIP), _FLOOR, PROFILE_CLIP)
    edges = np.linspace(0, len(d), bins + 1).astype(np.int64)
    med = float(np.median(d))
    out = np.array(
        [float(np.median(d[a:b])) if b > a else med for a, b in itertools.pairwise(edges.tolist())]
    )
    return np.log10(out)


def store_profiles(store: object, idx: ArrayLike) -> dict[str, NDArray[np.float64]]:
    """Profile columns (`PROFILE_FEATURES`) of pairs ``idx`` of a `scanguard.dataset.PairStore`."""
    ix = np.asarray(idx, dtype=np.int64)
    rows = np.empty((len(ix), PROFILE_BINS))
    for r, i in enumerate(ix.tolist()):
        prev, cur, est = store.pair_points(i)  # type: ignore[attr-defined]
        rows[r] = residual_profile(prev, cur, est)
    return {name: rows[:, k] for k, name in enumerate(PROFILE_FEATURES)}
