"""Self-calibration: this robot's odometry noise, fitted from its own matches (no reference)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from scanguard.apps.run import run_recording
from scanguard.apps.self_calibration import fit_robot_noise, self_calibrate
from scanguard.geometry import compose
from scanguard.matching.registry import get_matcher
from scanguard.pairs.odometry import (
    HALF_NORMAL_MEDIAN,
    RAYLEIGH_MEDIAN,
    OdometryNoise,
    fit_odometry_noise,
    odometry_sigmas,
)
from scanguard.slam.config import RunConfig
from tests.helpers import make_sequence, room_segments


def _noisy_pairs(scale: float, n: int = 4000, seed: int = 0):
    """Odometry increments, and matches = odometry + noise ``scale`` x the base model's."""
    rng = np.random.default_rng(seed)
    odo = np.column_stack(
        [rng.uniform(0.0, 0.4, n), rng.normal(0.0, 0.02, n), rng.normal(0.0, 0.1, n)]
    )
    s_xy, s_th = odometry_sigmas(odo, OdometryNoise())
    noise = np.column_stack(
        [rng.normal(0, 1, n) * s_xy, rng.normal(0, 1, n) * s_xy, rng.normal(0, 1, n) * s_th]
    )
    # the estimate seen from the odometry is the noise: est = odo (+) noise
    est = compose(odo, scale * noise)
    return est, odo


def test_known_noise_scale_is_recovered() -> None:
    est, odo = _noisy_pairs(3.0)
    fit = fit_odometry_noise(est, odo)
    assert fit.n_pairs == 4000
    assert fit.trans_scale == pytest.approx(3.0, rel=0.05)
    assert fit.rot_scale == pytest.approx(3.0, rel=0.05)
    base = OdometryNoise()
    assert fit.noise.trans_floor == pytest.approx(base.trans_floor * fit.trans_scale)
    assert fit.noise.rot_per_m_deg == pytest.approx(base.rot_per_m_deg * fit.rot_scale)
    assert fit.noise.seed == base.seed
    # the constants are the medians of |N(0,1)| and of the length of two of them
    rng = np.random.default_rng(1)
    g = rng.normal(size=(200_000, 2))
    assert float(np.median(np.hypot(g[:, 0], g[:, 1]))) == pytest.approx(RAYLEIGH_MEDIAN, rel=0.01)
    assert float(np.median(np.abs(g[:, 0]))) == pytest.approx(HALF_NORMAL_MEDIAN, rel=0.01)


def test_a_minority_of_faults_does_not_move_the_fit() -> None:
    est, odo = _noisy_pairs(2.0)
    clean = fit_odometry_noise(est, odo)
    est = est.copy()
    est[::5, 0] += 1.0  # 20 % faulty matches, 1 m off
    dirty = fit_odometry_noise(est, odo)
    assert dirty.trans_scale == pytest.approx(clean.trans_scale, rel=0.2)


def test_the_fit_never_makes_the_model_stricter_and_needs_enough_pairs() -> None:
    est, odo = _noisy_pairs(0.5)
    fit = fit_odometry_noise(est, odo)
    assert (fit.trans_scale, fit.rot_scale) == (1.0, 1.0)
    few = fit_odometry_noise(est[:10], odo[:10])
    assert few.n_pairs == 0 and few.noise == OdometryNoise()
    nan = odo.copy()
    nan[:] = np.nan  # no odometry at all
    assert fit_odometry_noise(est, nan).n_pairs == 0


class _OdometryReader:
    """A stand-in detector that reads the odometry disagreement (records the noise it gets)."""

    reads_odometry = True
    threshold = 0.5

    def __init__(self) -> None:
        self.odometry_noise = OdometryNoise()

    def use_odometry_noise(self, noise: OdometryNoise) -> None:
        self.odometry_noise = noise

    def fault_probability(self, *args: object, **kwargs: object) -> float:
        return 0.0


def _room_with_odometry(scale: float, n: int = 120):
    rng = np.random.default_rng(4)
    steps = np.tile([0.05, 0.0, 0.02], (n - 1, 1))
    seq = make_sequence(room_segments(), steps)
    s_xy, s_th = odometry_sigmas(steps, OdometryNoise())
    noisy = steps + scale * np.column_stack(
        [
            rng.normal(size=n - 1) * s_xy,
            rng.normal(size=n - 1) * s_xy,
            rng.normal(size=n - 1) * s_th,
        ]
    )
    odom = np.vstack([np.zeros(3), np.zeros((n - 1, 3))])
    for i in range(1, n):
        odom[i] = compose(odom[i - 1], noisy[i - 1])
    return replace(seq, odometry=odom)


def test_self_calibration_fits_a_recording_and_hands_the_model_to_the_detector() -> None:
    seq = _room_with_odometry(4.0)
    det = _OdometryReader()
    learned = self_calibrate(seq, seq.odometry, get_matcher("icp-paper"), det)
    assert learned is not None and learned["odometry_noise_pairs"] >= 100
    # ICP on a clean synthetic room is near exact: the fit sees the odometry's own noise
    assert learned["odometry_noise_trans_scale"] == pytest.approx(4.0, rel=0.35)
    assert det.odometry_noise.trans_floor == pytest.approx(
        OdometryNoise().trans_floor * learned["odometry_noise_trans_scale"]
    )
    # nothing to learn without odometry, or for a detector that does not read it
    assert self_calibrate(seq, None, get_matcher("icp-paper"), det) is None
    fit = fit_robot_noise(seq, seq.odometry, get_matcher("icp-paper"), OdometryNoise(), max_pairs=5)
    assert fit.n_pairs == 0  # too few pairs: the base model


def test_run_reports_what_it_learned(tmp_path) -> None:
    seq = _room_with_odometry(4.0, n=60)
    det = _OdometryReader()
    cfg = RunConfig(backend="frontend")
    cfg.guard.fit_odometry_noise = True
    res = run_recording(seq, det, tmp_path / "out", config=cfg)
    assert res.learned["odometry_noise_trans_scale"] > 1.5
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "- learned from this recording" in md.split("\n\n")[1]
    saved = json.loads((tmp_path / "out" / "metrics.json").read_text())["learned"]
    assert math.isclose(
        saved["odometry_noise_trans_scale"], res.learned["odometry_noise_trans_scale"]
    )
    # off by default: nothing learned, the detector keeps its model
    det2 = _OdometryReader()
    res2 = run_recording(seq, det2, tmp_path / "off", config=RunConfig(backend="frontend"))
    assert res2.learned == {} and det2.odometry_noise == OdometryNoise()
