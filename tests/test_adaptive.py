"""The adaptive operating point (`scanguard.detect.adaptive`): known answers on seeded streams."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.detect.adaptive import (
    AdaptiveConfig,
    AdaptiveOperatingPoint,
    AdaptiveThreshold,
    half_sample_mode,
    logit,
    mode_and_spread,
    replay,
    sigmoid,
    sorted_mode_and_spread,
    with_operating_point,
)
from scanguard.errors import ModelError
from scanguard.slam.gate import Gate
from scanguard.slam.guard import GuardConfig, operating_point_detector
from scanguard.slam.judge import Verdict

T0 = 0.25  # calibrated threshold: logit -1.0986


def _stream(seed: int = 0, n: int = 600, mode: float = 2.0, fault_every: int = 10) -> tuple:
    """Logits of a normal mode N(mode, 0.5) with a fault (mode + 6) every ``fault_every``."""
    rng = np.random.default_rng(seed)
    u = rng.normal(mode, 0.5, n)
    fault = np.zeros(n, dtype=bool)
    fault[fault_every - 1 :: fault_every] = True
    u[fault] = mode + 6.0 + rng.normal(0.0, 0.5, fault.sum())
    return 1.0 / (1.0 + np.exp(-u)), fault


def test_logit_sigmoid_round_trip() -> None:
    for p in (1e-6, 0.1, 0.5, 0.9, 1 - 1e-6):
        assert sigmoid(logit(p)) == pytest.approx(p, rel=1e-9)
    assert math.isfinite(logit(0.0)) and math.isfinite(logit(1.0))
    assert sigmoid(-800.0) == 0.0 and sigmoid(800.0) == 1.0


def test_half_sample_mode_ignores_a_large_upper_cluster() -> None:
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(-2.0, 0.3, 280), rng.normal(3.0, 1.0, 270)])
    assert half_sample_mode(x) == pytest.approx(-2.0, abs=0.15)
    assert float(np.median(x)) > -1.5  # the median is pulled up by the upper cluster


def test_converges_to_mode_plus_k_spread() -> None:
    p, _ = _stream(seed=0)
    op = AdaptiveOperatingPoint(T0, AdaptiveConfig(location="half_sample_mode", k=3.0))
    for v in p:
        op.observe(float(v))
    # normal mode N(2, 0.5): mode 2, lower MAD spread 0.5 -> threshold 3.5 (+- sampling)
    assert op.mode == pytest.approx(2.0, abs=0.2)
    assert op.spread == pytest.approx(0.5, abs=0.1)
    assert op.logit_threshold == pytest.approx(3.5, abs=0.35)
    assert op.logit_threshold == pytest.approx(op.mode + 3.0 * op.spread)


def test_faults_above_the_threshold_are_faults() -> None:
    p, fault = _stream(seed=2)
    called, used = replay(p, T0, AdaptiveConfig(location="half_sample_mode", k=3.0))
    after = np.arange(len(p)) >= 60
    # every injected fault is called; the normal mode (which the fixed 0.25 flags entirely)
    # is passed but for its far tail
    assert called[fault & after].all()
    assert called[~fault & after].mean() < 0.03
    assert (p[~fault & after] >= T0).all()
    assert used[-1] > 0.9  # logit 2 + 3 x 0.5: about 0.97


def test_warm_up_uses_the_calibrated_threshold() -> None:
    p, _ = _stream(seed=3)
    cfg = AdaptiveConfig(warmup=40)
    called, used = replay(p, T0, cfg)
    # the first 40 scores are judged against T0; the 41st against the 40 before it
    assert np.allclose(used[:40], T0)
    assert called[:40].all()  # the whole normal mode is above 0.25
    assert used[40] > 0.9


def test_causal_a_score_never_moves_its_own_threshold() -> None:
    p, _ = _stream(seed=4)
    _, used = replay(p, T0)
    q = p.copy()
    q[300:] = 0.999999  # change the future only
    _, used_q = replay(q, T0)
    assert np.array_equal(used[:301], used_q[:301])
    assert not np.array_equal(used[301:], used_q[301:])


def test_seeded_and_deterministic() -> None:
    p, _ = _stream(seed=5)
    a, ta = replay(p, T0)
    b, tb = replay(p, T0)
    assert np.array_equal(a, b) and np.array_equal(ta, tb)


def test_floor_and_ceiling() -> None:
    low = np.full(300, 1e-4)  # a mode far below the calibrated threshold
    _, used = replay(low, T0, AdaptiveConfig(floor=True))
    assert used[-1] == pytest.approx(T0)
    _, used = replay(low, T0, AdaptiveConfig(floor=False))
    assert used[-1] < T0
    high = np.full(300, 1 - 1e-9)  # a run of faults must not make faults normal
    _, used = replay(high, T0, AdaptiveConfig(max_probability=0.9))
    assert used[-1] == pytest.approx(0.9)


def test_non_finite_is_a_fault_and_is_not_learned() -> None:
    op = AdaptiveOperatingPoint(T0)
    assert op.is_fault(float("nan"))
    op.observe(float("nan"))
    assert op.n_seen == 0
    with pytest.raises(ModelError):
        AdaptiveOperatingPoint(1.0)


class _Fixed:
    """A detector that returns the probabilities of a list, in order."""

    threshold = T0
    source = "fixed-list"

    def __init__(self, values: np.ndarray) -> None:
        self.values = iter(values.tolist())

    def fault_probability(self, *_args: object, **_kwargs: object) -> float:
        return float(next(self.values))

    def predict_images(self, images: np.ndarray, **_kwargs: object) -> np.ndarray:
        return np.array([next(self.values) for _ in range(len(images))])


def test_wrapper_behind_the_detector_interface_decides_like_the_operating_point() -> None:
    p, _ = _stream(seed=6)
    expected, _ = replay(p, T0)
    wrapped = AdaptiveThreshold(_Fixed(p))
    gate = Gate("cnn", cnn_threshold=wrapped.threshold)  # the gate, unchanged
    got = [not gate.decide(Verdict(wrapped.fault_probability())).accepted for _ in p[:300]]
    got += [not gate.decide(Verdict(float(q))).accepted for q in wrapped.predict_images(p[300:])]
    assert np.array_equal(np.array(got), expected)
    assert wrapped.threshold == T0 and wrapped.current_threshold > 0.9
    assert wrapped.source == "fixed-list"  # everything else is the wrapped detector's
    assert wrapped.summary()["n_scores"] == len(p)


def test_config_switch() -> None:
    det = _Fixed(np.zeros(1))
    # unset: adaptive with the graph and GMapping, fixed with the scan-to-scan front end
    for backend in ("graph", "gmapping"):
        wrapped = operating_point_detector(GuardConfig(), det, backend)
        assert isinstance(wrapped, AdaptiveThreshold)
    assert operating_point_detector(GuardConfig(), det) is det
    assert operating_point_detector(GuardConfig(operating_point="fixed"), det, "graph") is det
    forced = operating_point_detector(GuardConfig(operating_point="adaptive"), det, "frontend")
    assert isinstance(forced, AdaptiveThreshold)
    cfg = GuardConfig(operating_point="adaptive", cnn_threshold=0.4, adaptive={"k": 2.0})
    wrapped = operating_point_detector(cfg, det)
    assert isinstance(wrapped, AdaptiveThreshold)
    assert wrapped.threshold == 0.4 and wrapped.operating_point.config.k == 2.0
    assert with_operating_point(det, "fixed") is det


@pytest.mark.parametrize("location", ["quantile", "median"])
@pytest.mark.parametrize("q", [0.3, 0.5, 0.1, 0.77])
def test_the_sorted_window_gives_numpys_numbers_bit_for_bit(location: str, q: float) -> None:
    """The O(window) mode and spread equal numpy's quantile and medians exactly."""
    rng = np.random.default_rng(7)
    cfg = AdaptiveConfig(location=location, location_quantile=q)  # type: ignore[arg-type]
    for n in (1, 2, 3, 4, 5, 30, 199, 200):
        for _ in range(60):
            u = rng.normal(1.0, 2.0, n)
            if rng.random() < 0.3:  # ties, and values equal to the location
                u = np.round(u, 1)
            fast = sorted_mode_and_spread(sorted(u.tolist()), cfg)
            assert fast is not None
            loc, spread = mode_and_spread(u, cfg)
            assert fast[0] == loc and fast[1] == spread, (n, u)
    assert sorted_mode_and_spread([0.0], AdaptiveConfig(spread="mad")) is None
    assert sorted_mode_and_spread([0.0], AdaptiveConfig(location="half_sample_mode")) is None


def test_thresholds_over_a_long_stream_equal_the_numpy_window() -> None:
    """Every threshold of a 1000-score stream (window 200) is the one numpy computes."""
    p, _ = _stream(seed=3, n=1000)
    p[::37] = 0.5  # repeated scores leave and enter the window
    op = AdaptiveOperatingPoint(T0)
    cfg = op.config
    window: list[float] = []
    for v in p:
        op.observe(float(v))
        window = [*window, logit(float(v))][-cfg.window :]
        if len(window) >= cfg.warmup:
            loc, spread = mode_and_spread(np.array(window), cfg)
            tau = max(min(loc + cfg.k * spread, logit(cfg.max_probability)), logit(T0))
            assert op.logit_threshold == tau and op.mode == loc and op.spread == spread
