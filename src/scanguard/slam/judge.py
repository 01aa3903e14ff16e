"""The judge: one matched scan pair in, one `Verdict` out (CNN fault probability, classical score).

`Judge.__call__(previous, current, match, odometry) -> Verdict` renders the pair and asks the
CNN (`Detector`) and the classical detector (`PairJudge`) for their fault estimates, and does
nothing else: what to do with a verdict is the `scanguard.slam.gate.Gate`'s business. It has
the shape of `scanguard.slam.graph.closure.ClosureJudge` (one candidate in, one verdict out).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.geometry import as_pose
from scanguard.pairs.features import pair_features
from scanguard.scan import LaserScan
from scanguard.slam.grid import robot_to_sensor_increment
from scanguard.slam.pair import Frame

logger = logging.getLogger(__name__)

_NAN = float("nan")


class Detector(Protocol):
    """Fault detector judged on the matched pair (`detect.detector.FaultDetector` fits)."""

    @property
    def threshold(self) -> float:
        """Probability at or above which a match is a fault."""
        ...

    def fault_probability(self, previous: LaserScan, current: LaserScan, pose: ArrayLike) -> float:
        """Probability that ``pose`` mis-aligns ``current`` onto ``previous``."""
        ...


class PairJudge(Protocol):
    """A classical (baseline) detector that may use the whole match result (its metrics)."""

    @property
    def name(self) -> str:
        """Short display name."""
        ...

    @property
    def threshold(self) -> float:
        """Score at or above which a match is a fault."""
        ...

    def score(self, previous: LaserScan, current: LaserScan, match: Any) -> float:
        """Fault score (probability-like, higher = more likely faulty)."""
        ...


@dataclass(frozen=True, slots=True)
class Verdict:
    """What the judge says about one matched pair.

    Attributes:
        fault_probability: CNN fault probability (None when the CNN was not asked).
        baseline_score: Classical fault score (None when the classical detector was not asked).
        reference_label: Label of the match against the reference (`scanguard.pairs.labels`),
            set by a caller that has a reference (the ``oracle`` gate reads it); None without.
        detect_seconds: Time of the render and the CNN.
        baseline_seconds: Time of the classical detector.
        wheel_supported: The scan's points support the wheels over the last matches
            (`scanguard.slam.wheel_support`), set by a caller that keeps that window.
    """

    fault_probability: float | None = None
    baseline_score: float | None = None
    reference_label: int | None = None
    detect_seconds: float = 0.0
    baseline_seconds: float = 0.0
    wheel_supported: bool = False

    @property
    def probability(self) -> float:
        """The CNN fault probability, NaN when not computed."""
        return _NAN if self.fault_probability is None else self.fault_probability

    @property
    def score(self) -> float:
        """The classical fault score, NaN when not computed."""
        return _NAN if self.baseline_score is None else self.baseline_score


def check_detector_matcher(detector: Any, matcher: Any, *, allow_other: bool = False) -> bool:
    """Check that ``detector`` was trained on the matches of ``matcher``.

    Only a detector that knows its matchers (``check_matcher``, as
    `scanguard.detect.detector.FaultDetector`) is checked. ``matcher`` is a registered name or a
    matcher object; an object without a ``name`` cannot be checked (logged as a warning).

    Args:
        detector: The CNN detector.
        matcher: Matcher name or object.
        allow_other: Accept a matcher the model was not trained for (logged as a warning).

    Returns:
        True when the detector was trained for the matcher (or cannot tell), False when it was
        not but ``allow_other`` is set.

    Raises:
        ModelError: The detector was not trained for the matcher and ``allow_other`` is off.
    """
    check = getattr(detector, "check_matcher", None)
    if not callable(check):
        return True
    name = matcher if isinstance(matcher, str) else getattr(matcher, "name", None)
    if not isinstance(name, str) or not name:
        logger.warning(
            "matcher %s has no name: cannot check that the model was trained on its matches",
            type(matcher).__name__,
        )
        return True
    return bool(check(name, allow_other=allow_other))


def _detector_features(detector: Any) -> list[str]:
    """Feature names a `scanguard.detect.baselines` detector reads."""
    if hasattr(detector, "feature"):
        return [str(detector.feature)]
    return [str(f) for f in (getattr(detector, "features", None) or [])]


class BaselineJudge:
    """A `scanguard.detect.baselines` detector (features -> fault score) as a `PairJudge`.

    The features of a pair are exactly those the dataset stores for training
    (`scanguard.pairs.features.pair_features`): the match's ``metrics()`` plus, when the
    detector reads a GMapping feature, `scanguard.matching.quality.gmapping_score` of the pair
    (the raw sum; ``gmapping_score_norm`` is derived by the detector as in training). The
    GMapping score is only computed when needed (it costs about as much as the ICP).

    Args:
        detector: A fitted `ThresholdDetector`, `MetricsModelDetector` or anything with
            ``name``, ``threshold`` and ``predict_proba(features)``.
        source: Where it came from (shown in reports).
    """

    def __init__(self, detector: Any, source: str = "<memory>") -> None:
        self.detector = detector
        self.source = source
        self.features = _detector_features(detector)
        self._needs_gmapping = any(f.startswith("gmapping") for f in self.features)

    @property
    def name(self) -> str:
        """The detector's display name."""
        return str(self.detector.name)

    @property
    def threshold(self) -> float:
        """Score at or above which a match is a fault (same decision as ``predict``)."""
        from scanguard.detect.baselines.threshold import ThresholdDetector

        if isinstance(self.detector, ThresholdDetector):
            # it flags strictly past its threshold, where predict_proba is exactly 0.5
            return float(np.nextafter(0.5, 1.0))
        return float(self.detector.threshold)

    def pair_features(self, previous: LaserScan, current: LaserScan, match: Any) -> dict[str, Any]:
        """Feature columns (length 1) of one matched pair."""
        return pair_features(previous, current, match, gmapping=self._needs_gmapping)

    def score(self, previous: LaserScan, current: LaserScan, match: Any) -> float:
        """Fault score of the detector for one matched pair (higher = more likely a fault)."""
        feats = self.pair_features(previous, current, match)
        return float(self.detector.predict_proba(feats)[0])

    def __repr__(self) -> str:
        return f"BaselineJudge({self.detector!r}, source={self.source!r})"


def cnn_fault_probability(
    detector: Any,
    previous: Frame,
    current: Frame,
    pose: NDArray[np.float64],
    match: Any = None,
    odometry: NDArray[np.float64] | None = None,
) -> float:
    """The CNN's fault probability of one matched pair (``odometry``: sensor-frame increment)."""
    style = getattr(detector, "style", None)
    if style is not None and callable(getattr(detector, "predict_images", None)):
        # `FaultDetector`: render the points already computed for the matcher (the very
        # arrays its own `render` would compute from the scans, so the image is identical)
        from scanguard.detect.render import render_pair

        image = render_pair(previous.points, current.points, pose, style)
        if getattr(detector, "metric_names", None):  # hybrid model: also reads the ICP metrics
            if getattr(detector, "reads_odometry", False):
                feats = detector.match_features(previous.points, current.points, match, odometry)
            else:
                feats = detector.match_features(previous.points, current.points, match)
            return float(detector.predict_images(image[None], features=feats)[0])
        return float(detector.predict_images(image[None])[0])
    return float(detector.fault_probability(previous.scan, current.scan, pose))


class Judge:
    """Judges matched scan pairs with a CNN and/or a classical detector.

    Args:
        detector: The CNN detector (None: not asked, ``fault_probability`` is None).
        baseline: The classical detector (None: not asked, ``baseline_score`` is None).
        laser_offset: Pose of the laser in the robot frame (odometry goes to the sensor frame).
        use_odometry: Hand the odometry to the detector (False: the detector judges the
            match's geometry alone, its odometry input masked as for a robot without one).
        odometry_below_eig: With ``use_odometry`` False, still hand the odometry over for a
            degenerate match: one whose ``eig_min_per_inlier`` (the matcher's weakest
            constrained direction, scale-free) is below this; None: never.
    """

    def __init__(
        self,
        detector: Detector | None = None,
        baseline: PairJudge | None = None,
        *,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
        use_odometry: bool = True,
        odometry_below_eig: float | None = None,
    ) -> None:
        self.detector = detector
        self.baseline = baseline
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self.use_odometry = use_odometry
        self.odometry_below_eig = odometry_below_eig

    def __call__(
        self,
        previous: Frame,
        current: Frame,
        match: Any,
        odometry: NDArray[np.float64] | None = None,
    ) -> Verdict:
        """The verdict on ``match`` (``current`` in ``previous``'s sensor frame).

        Args:
            previous: The previous scan (with its points).
            current: The current scan (with its points).
            match: The matcher's result (its ``pose`` is judged).
            odometry: Robot-frame odometry increment between the scans, or None.
        """
        pose = np.asarray(match.pose, dtype=np.float64)
        p_cnn = s_base = None
        t_cnn = t_base = 0.0
        if self.detector is not None:
            t = time.perf_counter()
            odo = None
            if odometry is not None and self._reads_odometry(match):
                odo = robot_to_sensor_increment(odometry, self.laser_offset)
            p_cnn = cnn_fault_probability(self.detector, previous, current, pose, match, odo)
            t_cnn = time.perf_counter() - t
        if self.baseline is not None:
            t = time.perf_counter()
            s_base = float(self.baseline.score(previous.scan, current.scan, match))
            t_base = time.perf_counter() - t
        return Verdict(p_cnn, s_base, detect_seconds=t_cnn, baseline_seconds=t_base)

    def _reads_odometry(self, match: Any) -> bool:
        """Whether the detector reads the odometry for this match (see the class docstring)."""
        if self.use_odometry:
            return True
        if self.odometry_below_eig is None:
            return False
        metrics = getattr(match, "metrics", None)
        eig = dict(metrics()).get("eig_min_per_inlier") if callable(metrics) else None
        # a match the scan does not constrain (a corridor) is where the wheels arbitrate
        return eig is not None and not float(eig) >= self.odometry_below_eig
