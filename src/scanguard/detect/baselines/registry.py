"""The default baselines by name, and saving / loading fitted detectors (JSON)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from scanguard.detect.baselines.base import SCALE_FREE_METRICS_FEATURES, FeatureDetector
from scanguard.detect.baselines.metrics_model import MetricsModelDetector
from scanguard.detect.baselines.threshold import ThresholdDetector
from scanguard.errors import ConfigError, ModelError
from scanguard.fsutil import atomic_write_text
from scanguard.io.base import printable
from scanguard.pairs.odometry import ODOMETRY_FEATURES
from scanguard.safeload import load_json

# Every feature read here is in SCALE_FREE_METRICS_FEATURES (checked by the tests): a baseline
# fitted on simulated pairs means the same on a real robot.
BASELINES: dict[str, Callable[[], FeatureDetector]] = {
    "residual": lambda: ThresholdDetector("mean_residual", "high", name="residual"),
    "overlap": lambda: ThresholdDetector("inlier_ratio", "low", name="overlap"),
    # Per inlier: the raw eigenvalue grows with the number of matched points, which differs
    # between sensors; the plain ``eig_min`` is available as ThresholdDetector("eig_min", "low").
    "degeneracy": lambda: ThresholdDetector("eig_min_per_inlier", "low", name="degeneracy"),
    # Per beam: the raw GMapping score grows with the number of beams.
    "gmapping": lambda: ThresholdDetector("gmapping_score_norm", "low", name="gmapping"),
    "metrics-model": lambda: MetricsModelDetector(name="metrics-model"),
}
"""Default baselines of the evaluation table: name -> factory of an unfitted detector.

All read only scale-free features (`SCALE_FREE_METRICS_FEATURES`) and choose their threshold
by `THRESHOLD_RULE` when fitted with a selection set."""


ODOMETRY_BASELINES: dict[str, Callable[[], FeatureDetector]] = {
    # the chi-like test a careful user with wheel odometry writes first: the larger of the
    # translational and rotational disagreement, in standard deviations of the noise model
    "odometry": lambda: ThresholdDetector("odom_max_z", "high", name="odometry"),
    "metrics+odometry": lambda: MetricsModelDetector(
        [*SCALE_FREE_METRICS_FEATURES, *ODOMETRY_FEATURES], name="metrics+odometry"
    ),
}
"""Classical detectors that also read the odometry disagreement (`scanguard.pairs.odometry`).

They need the odometry features of a pair store (`scanguard.detect.features.store_features`),
so they take part in evaluations, not in ``run``'s baseline instance; on pairs without
odometry the features are 0 and the mask says so."""


def make_baseline(name: str) -> FeatureDetector:
    """A new, unfitted baseline from `BASELINES` or `ODOMETRY_BASELINES`.

    Raises:
        ConfigError: Unknown name (the message lists the known ones).
    """
    known = {**BASELINES, **ODOMETRY_BASELINES}
    try:
        return known[name]()
    except KeyError:
        raise ConfigError(f"unknown baseline {name!r}; known: {', '.join(sorted(known))}") from None


def save_detector(detector: FeatureDetector, path: str | Path) -> Path:
    """Write a (fitted) detector as JSON, atomically."""
    p = Path(path)
    atomic_write_text(p, json.dumps(detector.to_dict(), indent=1))
    return p


def load_detector(path: str | Path) -> FeatureDetector:
    """Load a detector written by `save_detector` (plain JSON: nothing is unpickled).

    Raises:
        ModelError: Missing, not a regular file, not JSON (or nested too deep), or not a
            detector file (an unknown type, ``features`` not a list of names, a model entry
            that is not a fitted model), or a file of the former pickled format (the message
            says how to convert it); one line naming the file.
    """
    p = Path(path)
    data = load_json(p, what="detector file", error=ModelError)
    if not isinstance(data, dict):
        raise ModelError(f"{p}: not a detector file (a JSON {type(data).__name__})")
    kind = data.get("type")
    if kind not in ("threshold", "metrics-model"):
        raise ModelError(f"{p}: unknown detector type {printable(str(kind))!r}")
    feats = data.get("features")
    # a string would be read as a list of one-letter feature names
    if feats is not None and not (
        isinstance(feats, list) and feats and all(isinstance(f, str) for f in feats)
    ):
        raise ModelError(f"{p}: features must be a list of feature names, not {_what(feats)}")
    if "feature" in data and not isinstance(data["feature"], str):
        raise ModelError(f"{p}: feature must be a feature name, not {_what(data['feature'])}")
    try:
        det: FeatureDetector
        if kind == "threshold":
            det = ThresholdDetector.from_dict(data)
        else:
            det = MetricsModelDetector.from_dict(data)
    except ModelError as exc:
        raise ModelError(f"{p}: {exc}") from None
    except _DECODE_ERRORS as exc:
        problem = printable(" ".join(str(exc).split()) or type(exc).__name__, 120)
        raise ModelError(f"{p}: not a valid detector file ({problem})") from None
    return det


# what decoding a hand-edited or corrupt file can raise (nothing is unpickled any more)
_DECODE_ERRORS = (
    ValueError,
    KeyError,
    TypeError,
    AttributeError,
    IndexError,
    RecursionError,
)


def _what(value: object) -> str:
    return f"a {type(value).__name__}" if value is not None else "null"
