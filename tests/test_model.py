from __future__ import annotations

import numpy as np
import pytest
import torch
from numpy.typing import NDArray

from scanguard.detect.model import PRESETS, FaultCNN, ModelConfig, build_model, count_parameters
from scanguard.errors import ConfigError
from scanguard.geometry import compose, relative
from scanguard.scan import SensorInfo
from tests.helpers import make_scan, room_segments

SMALL_SENSOR = SensorInfo(
    name="small",
    n_beams=360,
    angle_min=-np.pi,
    angle_increment=2 * np.pi / 360,
    range_min=0.1,
    range_max=20.0,
    rate_hz=10.0,
)


def synthetic_pairs(
    n: int, seed: int = 0
) -> tuple[
    list[NDArray[np.float32]], list[NDArray[np.float32]], NDArray[np.float64], NDArray[np.int64]
]:
    """Scan pairs in the test room with exact (normal) or perturbed (fault) estimates.

    Faults displace the estimate by 0.4-1.0 m or 8-25 degrees, normals by at most 1 cm /
    0.3 degrees, so the classes are clearly separable in the images.
    """
    rng = np.random.default_rng(seed)
    segs = room_segments()
    prev, cur, est, lab = [], [], [], []
    for i in range(n):
        a = np.array([rng.uniform(-3.5, 3.5), rng.uniform(-2.0, 2.0), rng.uniform(-np.pi, np.pi)])
        step = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1), rng.uniform(-0.2, 0.2)])
        b = compose(a, step)
        true = relative(a, b)
        fault = i % 2 == 1
        if fault:
            if rng.random() < 0.5:
                ang = rng.uniform(0, 2 * np.pi)
                d = rng.uniform(0.4, 1.0)
                err = np.array([d * np.cos(ang), d * np.sin(ang), 0.0])
            else:
                err = np.array([0.0, 0.0, np.radians(rng.uniform(8, 25)) * rng.choice([-1, 1])])
        else:
            err = np.array([*rng.normal(0, 0.005, 2), np.radians(rng.normal(0, 0.1))])
        prev.append(make_scan(segs, a, sensor=SMALL_SENSOR, noise=0.01, rng=rng).points())
        cur.append(make_scan(segs, b, sensor=SMALL_SENSOR, noise=0.01, rng=rng).points())
        est.append(compose(true, err))
        lab.append(int(fault))
    return prev, cur, np.array(est), np.array(lab, dtype=np.int64)


def test_paper_preset_layer_structure() -> None:
    m = build_model("paper")
    cfg = m.config
    assert (cfg.in_channels, cfg.input_size) == (3, 256)
    convs = [x for x in m.features if isinstance(x, torch.nn.Conv2d)]
    pools = [x for x in m.features if isinstance(x, torch.nn.MaxPool2d)]
    drops = [x for x in m.features if isinstance(x, torch.nn.Dropout)]
    relus = [x for x in m.features if isinstance(x, torch.nn.ReLU)]
    assert len(convs) == len(pools) == len(drops) == len(relus) == 5
    assert [c.out_channels for c in convs] == [32, 64, 128, 128, 256]
    assert all(p.kernel_size == 2 for p in pools)
    assert all(d.p == 0.25 for d in drops)
    # block order: conv, relu, pool, dropout
    kinds = [type(x).__name__ for x in m.features]
    assert kinds[:4] == ["Conv2d", "ReLU", "MaxPool2d", "Dropout"]
    linears = [x for x in m.classifier if isinstance(x, torch.nn.Linear)]
    assert [(x.in_features, x.out_features) for x in linears] == [(256 * 8 * 8, 256), (256, 2)]
    x = torch.rand(2, 3, 256, 256)
    out = m(x)
    assert out.shape == (2, 2)
    p = torch.softmax(out, 1)
    assert torch.allclose(p.sum(1), torch.ones(2))
    assert torch.allclose(m.fault_probability(x), p[:, 1])


def test_compact_preset_is_half_width_and_small() -> None:
    paper, compact = PRESETS["paper"], PRESETS["compact"]
    assert [w * 2 for w in compact.widths] == paper.widths
    assert compact.in_channels == 2
    m = build_model("compact")
    assert count_parameters(m) < 500_000
    assert m(torch.rand(3, 2, compact.input_size, compact.input_size)).shape == (3, 2)


def test_bad_configs_are_rejected() -> None:
    with pytest.raises(ConfigError, match="unknown model preset"):
        build_model("nope")
    with pytest.raises(ConfigError, match="not divisible"):
        FaultCNN(ModelConfig(input_size=100))


def test_build_is_seeded() -> None:
    torch.manual_seed(3)
    a = build_model("tiny")
    torch.manual_seed(3)
    b = build_model("tiny")
    for (ka, va), (_, vb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert torch.equal(va, vb), ka


def test_synthetic_pairs_have_the_promised_errors() -> None:
    _, _, est, lab = synthetic_pairs(6, seed=1)
    assert lab.tolist() == [0, 1, 0, 1, 0, 1]
    assert est.shape == (6, 3)


def test_multiscale_and_hybrid_presets() -> None:
    from scanguard.detect.model import METRIC_FEATURES, build_model, get_preset

    ms = get_preset("multiscale")
    assert (ms.in_channels, ms.input_size, ms.metrics) == (6, 64, [])
    hy = build_model("cnn+metrics")
    assert hy.uses_metrics and hy.config.metrics == list(METRIC_FEATURES)
    x = torch.zeros(3, 6, 64, 64)
    with pytest.raises(ConfigError, match="ICP metrics"):
        hy(x)
    # late fusion (metric_hidden 0): image logits + a linear term of the standardised metrics
    torch.manual_seed(0)
    met = torch.randn(3, len(METRIC_FEATURES))
    hy.set_metric_scaling(np.full(7, 0.5), np.full(7, 2.0))
    want = hy.classifier(hy.features(x)) + hy.metric_net((met - 0.5) / 2.0)
    torch.testing.assert_close(hy(x, met), want)
    # hidden-layer fusion: flattened 128x2x2 image features + 16 metric units feed the dense
    cat = build_model(hy.config.model_copy(update={"metric_hidden": 16}))
    first_dense = next(m for m in cat.classifier if isinstance(m, torch.nn.Linear))
    assert first_dense.in_features == 128 * 2 * 2 + 16
    assert cat(x, met).shape == (3, 2)
    assert not build_model("multiscale").uses_metrics


def test_metric_inputs_known_answer() -> None:
    from scanguard.detect.model import metric_inputs

    feats = {
        "mean_residual": np.array([0.01, np.nan]),
        "inlier_ratio": np.array([0.9, 0.2]),
        "gmapping_score": np.array([50.0, 10.0]),
        "n_source": np.array([100.0, 0.0]),
        "eig_min": np.array([2.0, 1.0]),
        "n_inliers": np.array([200.0, 0.0]),
    }
    got = metric_inputs(
        feats, ["mean_residual", "inlier_ratio", "gmapping_score_norm", "eig_min_per_inlier"]
    )
    # log10(0.01) = -2; NaN residual (no match) -> 10 m -> 1; 50 / 100; log10(2 / 200) = -2;
    # zero counts give 0 (derived features), eig 0 -> floor 1e-6 -> -6
    np.testing.assert_allclose(got, [[-2.0, 0.9, 0.5, -2.0], [1.0, 0.2, 0.0, -6.0]], rtol=1e-6)
    assert got.dtype == np.float32
    with pytest.raises(ConfigError, match="iterations"):
        metric_inputs(feats, ["iterations"])
