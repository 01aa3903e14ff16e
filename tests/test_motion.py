"""The fused motion model: known answers for the information-weighted fusion and the wheel flag."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.slam.motion import (
    FusedMotion,
    FusionConfig,
    ThreeCorneredHat,
    WheelNoise,
    match_information,
)

SIGMA = 0.02


def _info(diag: tuple[float, float, float]) -> np.ndarray:
    return np.diag(np.asarray(diag, dtype=np.float64))


def test_match_information_without_offset_is_the_normalised_hessian() -> None:
    h = np.array([[50.0, 5.0, 1.0], [5.0, 80.0, -2.0], [1.0, -2.0, 300.0]])
    info = match_information(h, 100, [0.1, 0.0, 0.05], [0.0, 0.0, 0.0], SIGMA)
    np.testing.assert_allclose(info, h / 100 / SIGMA**2, rtol=1e-6)


def test_match_information_follows_the_laser_offset() -> None:
    # a laser mounted 0.3 m ahead, turned by 90 deg: its x is the robot's y
    h = np.diag([100.0, 0.0, 0.0]) + 1e-9 * np.eye(3)
    info = match_information(h, 100, [0.0, 0.0, 0.0], [0.3, 0.0, math.pi / 2], SIGMA)
    assert info[1, 1] == pytest.approx(1.0 / SIGMA**2, rel=1e-5)
    assert abs(info[0, 0]) < 1e-3


def test_equal_information_gives_the_mean_and_halves_the_covariance() -> None:
    cfg = FusionConfig(prediction_sigma_xy=1e3, prediction_sigma_theta=1e3, wheel_flag_chi2=None)
    fm = FusedMotion(cfg)
    wheel = np.array([0.10, 0.0, 0.02])
    sig_w = fm.wheels.sigma(wheel)
    info_m = np.diag(1.0 / sig_w**2)  # the match as sure as the wheels
    st = fm.step(0.1, wheel, np.array([0.12, 0.01, 0.00]), info_m, eig_min_per_inlier=1.0)
    np.testing.assert_allclose(st.increment, [0.11, 0.005, 0.01], atol=1e-6)
    np.testing.assert_allclose(np.diag(st.covariance), sig_w**2 / 2, rtol=1e-5)
    assert st.sources == "match+wheels+prediction" and not st.wheels_flagged


def test_a_corridor_match_leaves_the_corridor_axis_to_the_wheels() -> None:
    fm = FusedMotion(FusionConfig(wheel_flag_chi2=None))
    # the scan constrains y and theta, not x (a corridor along x)
    info = _info((1e-9, 1.0 / 0.002**2, 1.0 / 0.001**2))
    st = fm.step(0.1, np.array([0.20, 0.0, 0.0]), np.array([0.02, 0.03, 0.01]), info)
    # wheels along the corridor (the weak zero prediction of a first step pulls 1 %)
    assert st.increment[0] == pytest.approx(0.20, abs=3e-3)
    assert st.increment[2] == pytest.approx(0.01, abs=1e-4)  # the match across it
    assert st.increment[1] > 0.02


def test_a_normal_match_flags_wheels_that_lie() -> None:
    fm = FusedMotion(FusionConfig())
    info = _info((1.0 / SIGMA**2, 1.0 / SIGMA**2, 1.0 / 0.002**2))
    # the wheels say 0.3 m forward, the scans say 0.3 m backward (FR079's wheels)
    st = fm.step(0.1, np.array([0.3, 0.0, 0.0]), np.array([-0.3, 0.0, 0.0]), info,
                 eig_min_per_inlier=1.0)  # fmt: skip
    assert st.wheels_flagged and st.mahalanobis2 > 25.0
    assert "wheels" not in st.sources
    assert st.increment[0] == pytest.approx(-0.3, abs=2e-3)
    # a degenerate match may not flag them: nothing to trust over the wheels
    st = fm.step(0.1, np.array([0.3, 0.0, 0.0]), np.array([-0.3, 0.0, 0.0]), info,
                 eig_min_per_inlier=0.01)  # fmt: skip
    assert not st.wheels_flagged and "wheels" in st.sources
    # the unguarded comparison never flags them
    un = FusedMotion(FusionConfig(), flag_wheels=False)
    st = un.step(0.1, np.array([0.3, 0.0, 0.0]), np.array([-0.3, 0.0, 0.0]), info,
                 eig_min_per_inlier=1.0)  # fmt: skip
    assert not st.wheels_flagged and "wheels" in st.sources
    assert fm.counts["flagged"] == 1


def test_without_odometry_a_rejected_match_leaves_the_prediction() -> None:
    fm = FusedMotion(FusionConfig())
    info = _info((1.0 / SIGMA**2, 1.0 / SIGMA**2, 1.0 / 0.002**2))
    fm.step(0.1, None, np.array([0.05, 0.0, 0.01]), info)
    st = fm.step(0.2, None, None, None)  # twice the time: twice the motion
    assert st.sources == "prediction"
    np.testing.assert_allclose(st.increment, [0.1, 0.0, 0.02], atol=1e-3)
    assert fm.counts["prediction_only"] == 1


def test_the_wheels_vouch_for_a_rejected_match_that_agrees_with_them() -> None:
    rng = np.random.default_rng(7)
    cfg = FusionConfig(fit_min=20, vouch_chi2=7.81)
    fm = FusedMotion(cfg)
    info = _info((1.0 / 0.005**2, 1.0 / 0.005**2, 1.0 / 0.001**2))
    true = np.array([0.2, 0.0, 0.01])

    def wheel() -> np.ndarray:
        return true * np.array([1.02, 1.0, 0.97]) + 0.002 * rng.standard_normal(3)

    rejected = fm.step(0.5, wheel(), true.copy(), info, eig_min_per_inlier=1.0, rejected=True)
    assert rejected.sources == "wheels+prediction"  # wheels not fitted yet: no vouch
    for _ in range(30):  # normal matches fit the wheels' noise
        fm.step(0.5, wheel(), true + 0.001 * rng.standard_normal(3), info, eig_min_per_inlier=1.0)
    n_fit = fm.wheels.n_fitted
    st = fm.step(0.5, wheel(), true.copy(), info, eig_min_per_inlier=1.0, rejected=True)
    assert st.sources == "vouched_match+wheels+prediction" and st.mahalanobis2 < 7.81
    np.testing.assert_allclose(st.increment, true, atol=2e-3)  # the match's precision
    assert fm.wheels.n_fitted == n_fit  # a rejected match never fits the wheels
    # one that disagrees with the wheels stays out, and does not flag them
    far = true + np.array([0.15, 0.0, 0.0])
    st = fm.step(0.5, wheel(), far, info, eig_min_per_inlier=1.0, rejected=True)
    assert st.sources == "wheels+prediction" and not st.wheels_flagged
    # a degenerate one (a corridor) cannot be vouched for
    st = fm.step(0.5, wheel(), true.copy(), info, eig_min_per_inlier=0.01, rejected=True)
    assert st.sources == "wheels+prediction"
    # wheels that a normal match just caught lying vouch for nothing until found right again
    fm.step(0.5, true - np.array([0.3, 0.0, 0.0]), true.copy(), info, eig_min_per_inlier=1.0)
    st = fm.step(0.5, wheel(), true.copy(), info, eig_min_per_inlier=1.0, rejected=True)
    assert st.sources == "wheels+prediction"
    assert fm.counts["vouched_match"] == 1 and fm.counts["flagged"] == 1
    # off by default: the rejected match loses its term
    off = FusedMotion(FusionConfig(fit_min=20))
    for _ in range(30):
        off.step(0.5, wheel(), true.copy(), info, eig_min_per_inlier=1.0)
    st = off.step(0.5, wheel(), true.copy(), info, eig_min_per_inlier=1.0, rejected=True)
    assert st.sources == "wheels+prediction"


def test_angles_fuse_across_the_wrap() -> None:
    cfg = FusionConfig(prediction_sigma_xy=1e3, prediction_sigma_theta=1e3, wheel_flag_chi2=None)
    fm = FusedMotion(cfg)
    info = _info((1e4, 1e4, 1e4))
    st = fm.step(0.1, None, np.array([0.0, 0.0, math.pi - 0.01]), info)
    assert abs(abs(st.increment[2]) - (math.pi - 0.01)) < 1e-3


def test_wheel_noise_scale_is_fitted_from_matches() -> None:
    rng = np.random.default_rng(4)
    noise = WheelNoise(FusionConfig(fit_window=2000, fit_min=50))
    for _ in range(1500):
        wheel = np.array([rng.uniform(0.0, 0.2), rng.normal(0, 0.005), rng.normal(0, 0.05)])
        true = wheel + 2.0 * noise.base_sigma(wheel) * rng.standard_normal(3)
        noise.observe(wheel, true)
    np.testing.assert_allclose(noise.scale, [2.0, 2.0, 2.0], rtol=0.1)
    assert noise.n_fitted == 1500


def test_three_cornered_hat_separates_the_match_noise_from_the_wheel_noise() -> None:
    """Known sigmas: wheels 2x their model, matches 3x what their Hessian claims (variance 9x);
    the prediction errs by the robot's change of velocity. Each is recovered from the three
    pairwise disagreements alone."""
    rng = np.random.default_rng(11)
    hat = ThreeCorneredHat(FusionConfig(fit_window=4000, fit_min=50))
    base_w = np.array([0.004, 0.002, 0.003])  # GMapping's model sigma for these steps
    # what the Hessian says (variance); the three sources are of one order per axis: a source
    # far better than the other two is resolved only coarsely (its variance is a small
    # difference of large ones), the known limit of the method
    claimed_m = np.array([0.002, 0.002, 0.001]) ** 2
    velocity = np.array([0.1, 0.0, 0.02])
    for _ in range(4000):
        prediction = velocity.copy()
        velocity = velocity + rng.normal(0.0, [0.005, 0.002, 0.004])  # acceleration
        wheel = velocity + rng.normal(0.0, 2.0 * base_w)
        match = velocity + rng.normal(0.0, 3.0 * np.sqrt(claimed_m))
        hat.observe(wheel, match, prediction, claimed_m, base_w**2)
    np.testing.assert_allclose(hat.wheel_scale, [2.0, 2.0, 2.0], rtol=0.12)
    np.testing.assert_allclose(hat.match_scale, [9.0, 9.0, 9.0], rtol=0.25)
    assert hat.n_fitted == 4000


def test_three_cornered_fusion_trusts_the_better_source_more() -> None:
    """Fused with the fitted scales, a match that is worse than claimed weighs less."""
    cfg = FusionConfig(noise_fit="three_cornered", fit_min=5, fit_window=50)
    f = FusedMotion(cfg)
    info = _info((1 / SIGMA**2, 1 / SIGMA**2, 1 / 0.01**2))
    assert f.hat is not None
    f.hat.match_scale = np.array([4.0, 4.0, 4.0])
    step = f.step(0.1, np.array([0.1, 0.0, 0.0]), np.array([0.1, 0.0, 0.0]), info,
                  eig_min_per_inlier=1.0)  # fmt: skip
    # the match's variance is 4x its claim: its information a quarter
    scaled = f._scaled_match_information(info)
    np.testing.assert_allclose(np.diag(scaled), np.diag(info) / 4.0)
    assert step.sources == "match+wheels+prediction"


def test_defaults_fuse_judged_plicp_into_the_graph_and_the_paper_config_pins_gmapping() -> None:
    """The default chosen leave one log out (README), and the paper's configuration beside it."""
    from pathlib import Path

    from scanguard.slam.config import RunConfig

    cfg = RunConfig()
    assert (cfg.backend, cfg.motion, cfg.matcher) == ("graph", "fused", "plicp")
    assert cfg.maps_rejected_scans() and not cfg.judge_reads_odometry()
    # the wheel-flag limit: chi-square, three degrees of freedom, 99 %
    assert cfg.fusion.wheel_flag_chi2 == pytest.approx(11.3449, abs=1e-3)
    paper = RunConfig.from_yaml(Path(__file__).parents[1] / "configs" / "run_paper.yaml")
    assert (paper.backend, paper.motion) == ("gmapping", "odometry")
    assert not paper.maps_rejected_scans()


def test_a_doubted_match_keeps_a_say_that_falls_with_its_fault_probability() -> None:
    cfg = FusionConfig(prediction_sigma_xy=1e3, prediction_sigma_theta=1e3, doubted_weight=True)
    fm = FusedMotion(cfg)
    wheel = np.array([0.10, 0.0, 0.0])
    info_m = np.diag(1.0 / fm.wheels.sigma(wheel) ** 2)  # the match as sure as the wheels
    match = np.array([0.20, 0.0, 0.0])

    def rejected(p: float) -> object:
        return fm.step(0.1, wheel, match, info_m, eig_min_per_inlier=1.0, fault_probability=p,
                       rejected=True)  # fmt: skip

    st = rejected(0.5)  # information x 0.25: (0.25 * 0.20 + 0.10) / 1.25
    assert st.sources == "doubted_match+wheels+prediction" and not st.wheels_flagged
    assert st.increment[0] == pytest.approx(0.12, abs=1e-4)
    assert rejected(0.9).increment[0] == pytest.approx((0.01 * 0.2 + 0.1) / 1.01, abs=1e-4)
    assert rejected(1.0).sources == "wheels+prediction"  # a sure fault: no say
    assert rejected(math.nan).sources == "wheels+prediction"  # no probability (another gate)
    assert fm.counts["doubted_match"] == 2 and fm.counts["match"] == 0
    assert fm.wheels.n_fitted == 0  # a doubted match never fits the wheels
    alone = fm.step(0.1, None, match, info_m, fault_probability=0.5, rejected=True)
    assert alone.sources == "prediction"  # without wheels a rejected match has no say
    off = FusedMotion(FusionConfig(prediction_sigma_xy=1e3, prediction_sigma_theta=1e3))
    st = off.step(0.1, wheel, match, info_m, fault_probability=0.5, rejected=True)
    assert st.sources == "wheels+prediction"  # off (the default): it loses its term
