"""Features of a loop-closure candidate, all of them available to a judge at run time.

`candidate_features` gives every column of `FEATURES` (never errors or labels):

* the loop matcher's ``response`` and ``coarse_response``;
* the response-surface standard deviations ``std_x``, ``std_y``, ``std_theta`` and
  ``std_xy = max(std_x, std_y)``;
* how far the closure would move the graph: ``disagreement_m`` / ``disagreement_rad`` (the
  proposed against the graph's prior relative pose), the same per metre of ``path_gap``
  (``disagreement_m_per_m``, ``disagreement_rad_per_m``; drift grows with the path), and the
  ``path_gap`` itself, and ``disagreement_sigmas``: the correction in standard deviations of
  the graph's uncertainty about the two nodes' relative pose (plus the match's);
* the ICP quality metrics of the ``icp-paper`` matcher run on the pair (current scan onto the
  target node's scan) from the proposed pose, prefixed ``icp_`` (`ICP_METRICS`), plus
  ``icp_shift_m`` / ``icp_shift_rad``: how far that ICP moves away from the proposed pose.

The learned judge (`scanguard.slam.graph.judges.LearnedClosureJudge`) reads them for each
candidate; `scanguard.apps.closure_harvest` tabulates them for training.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from scanguard.detect.baselines.base import LEGACY_METRICS_FEATURES
from scanguard.geometry import as_pose, relative, wrap_angle
from scanguard.matching.registry import get_matcher

ICP_MATCHER = "icp-paper"
"""Matcher whose quality metrics describe a candidate pair (the shipped detector's)."""


ICP_METRICS: tuple[str, ...] = tuple(
    k for k in LEGACY_METRICS_FEATURES if k not in ("translation", "rotation")
)
"""Keys of `scanguard.matching.MatchResult.metrics` kept (prefixed ``icp_``)."""


CANDIDATE_FEATURES: tuple[str, ...] = (
    "response",
    "coarse_response",
    "std_x",
    "std_y",
    "std_theta",
    "std_xy",
    "disagreement_m",
    "disagreement_rad",
    "disagreement_m_per_m",
    "disagreement_rad_per_m",
    "path_gap",
    "disagreement_sigmas",
)
"""Features read from the candidate itself (matcher outputs and graph geometry)."""


FEATURES: tuple[str, ...] = (
    CANDIDATE_FEATURES + tuple(f"icp_{k}" for k in ICP_METRICS) + ("icp_shift_m", "icp_shift_rad")
)
"""Every feature column of `candidate_table` (plus ``cnn_proba`` when a detector is given)."""


_GAP_FLOOR = 1.0  # m: the per-metre disagreements of short loops are not blown up


def icp_features(record_or_candidate: Any, matcher: Any = None) -> dict[str, float]:
    """The ``icp_*`` features of one candidate (NaN when its scans are gone).

    Args:
        record_or_candidate: A `ClosureRecord` or a `ClosureCandidate`.
        matcher: Matcher to run (None = `ICP_MATCHER`).
    """
    cand = getattr(record_or_candidate, "candidate", record_or_candidate)
    names = [f"icp_{k}" for k in ICP_METRICS] + ["icp_shift_m", "icp_shift_rad"]
    if getattr(cand, "source", None) is None or getattr(cand, "target", None) is None:
        return dict.fromkeys(names, math.nan)
    matcher = matcher or get_matcher(ICP_MATCHER)
    pose = np.asarray(cand.pose, dtype=np.float64)
    m = matcher(cand.source.points(np.float64), cand.target.points(np.float64), pose)
    metrics = m.metrics()
    out = {f"icp_{k}": float(metrics.get(k, math.nan)) for k in ICP_METRICS}
    shift = relative(as_pose(pose), as_pose(np.asarray(m.pose, dtype=np.float64)))
    out["icp_shift_m"] = float(math.hypot(shift[0], shift[1]))
    out["icp_shift_rad"] = float(abs(wrap_angle(shift[2])))
    return out


def candidate_features(record_or_candidate: Any, matcher: Any = None) -> dict[str, float]:
    """All `FEATURES` of one candidate (a `ClosureRecord` or a `ClosureCandidate`)."""
    cand = getattr(record_or_candidate, "candidate", record_or_candidate)
    s = cand.std
    dm, dr = cand.disagreement
    gap = float(cand.path_gap)
    norm = max(gap, _GAP_FLOOR) if math.isfinite(gap) else math.nan
    out = {
        "response": float(cand.score),
        "coarse_response": float(cand.coarse_score),
        "std_x": float(s[0]),
        "std_y": float(s[1]),
        "std_theta": float(s[2]),
        "std_xy": float(max(s[0], s[1])),
        "disagreement_m": dm,
        "disagreement_rad": dr,
        "disagreement_m_per_m": dm / norm,
        "disagreement_rad_per_m": dr / norm,
        "path_gap": gap,
        "disagreement_sigmas": float(cand.disagreement_sigmas),
    }
    out.update(icp_features(cand, matcher))
    return out


__all__ = [
    "CANDIDATE_FEATURES",
    "FEATURES",
    "ICP_MATCHER",
    "ICP_METRICS",
    "candidate_features",
    "icp_features",
]
