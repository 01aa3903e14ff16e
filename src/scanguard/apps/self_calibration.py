"""Self-calibration on the user's own recording: no reference poses, no relations.

`fit_robot_noise` matches a spread of consecutive scan pairs of the recording the way the
guard does (the configured matcher, from the identity) and fits this robot's odometry noise
to the disagreement between those matches and the odometry
(`scanguard.pairs.odometry.fit_odometry_noise`): a detector that reads the odometry
disagreement then reads it in this robot's units, not in those of the simulator it was
trained on.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import relative
from scanguard.pairs.odometry import NoiseFit, OdometryNoise, fit_odometry_noise
from scanguard.scan import ScanSequence
from scanguard.slam.grid import robot_to_sensor_increment

logger = logging.getLogger(__name__)

#: Pairs matched for the fit, spread evenly over the recording.
FIT_PAIRS = 300


def fit_robot_noise(
    seq: ScanSequence,
    odometry: NDArray[np.float64],
    matcher: Any,
    base: OdometryNoise,
    *,
    min_points: int = 10,
    max_pairs: int = FIT_PAIRS,
) -> NoiseFit:
    """This robot's odometry noise, fitted from ``max_pairs`` of its consecutive scan pairs.

    Args:
        seq: The recording (scans and laser offset).
        odometry: ``(N, 3)`` robot odometry poses, one per scan.
        matcher: The guard's matcher (``matcher(source, target, initial) -> match``).
        base: The detector's noise model (what the fit scales).
        min_points: Pairs with fewer valid points in either scan are left out.
        max_pairs: How many pairs to match (evenly spread over the recording).

    Returns:
        The fit (the base model when too few pairs could be matched).
    """
    n = len(seq)
    picks = np.unique(np.linspace(0, n - 2, min(max_pairs, n - 1)).astype(np.int64))
    est: list[NDArray[np.float64]] = []
    odo: list[NDArray[np.float64]] = []
    for k in picks:
        prev = seq.scans[k].points(np.float64)
        cur = seq.scans[k + 1].points(np.float64)
        if len(prev) < min_points or len(cur) < min_points:
            continue
        match = matcher(cur, prev, None)
        est.append(np.asarray(match.pose, dtype=np.float64))
        inc = relative(odometry[k], odometry[k + 1])
        odo.append(robot_to_sensor_increment(inc, seq.laser_offset))
    if not est:
        return NoiseFit(base, 1.0, 1.0, 0)
    fit = fit_odometry_noise(np.array(est), np.array(odo), base)
    logger.info(
        "%s: odometry noise fitted on %d pairs: translation x%.2f, rotation x%.2f",
        seq.name,
        fit.n_pairs,
        fit.trans_scale,
        fit.rot_scale,
    )
    return fit


def self_calibrate(
    seq: ScanSequence,
    odometry: NDArray[np.float64] | None,
    matcher: Any,
    detector: Any,
    *,
    min_points: int = 10,
) -> dict[str, float] | None:
    """Fit the robot's odometry noise and hand it to ``detector``; what was learned.

    Nothing happens (None) when the recording has no odometry or the detector does not read
    the odometry disagreement.
    """
    if odometry is None or not getattr(detector, "reads_odometry", False):
        return None
    fit = fit_robot_noise(seq, odometry, matcher, detector.odometry_noise, min_points=min_points)
    detector.use_odometry_noise(fit.noise)
    return {
        "odometry_noise_trans_scale": fit.trans_scale,
        "odometry_noise_rot_scale": fit.rot_scale,
        "odometry_noise_pairs": float(fit.n_pairs),
        "odometry_noise_trans_floor": fit.noise.trans_floor,
        "odometry_noise_trans_per_m": fit.noise.trans_per_m,
        "odometry_noise_rot_floor_deg": fit.noise.rot_floor_deg,
    }
