"""The odometry input of the detector: known disagreements, the mask, the store, the guard."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scanguard.detect.detector import FaultDetector
from scanguard.detect.model import ODOMETRY_METRIC_FEATURES, ModelConfig, build_model, metric_inputs
from scanguard.detect.train_config import TrainConfig
from scanguard.detect.train_epoch import odometry_columns
from scanguard.geometry import compose, relative
from scanguard.matching import get_matcher
from scanguard.pairs.odometry import OdometryNoise, odometry_disagreement, odometry_sigmas
from scanguard.slam.grid import robot_to_sensor_increment
from scanguard.slam.guard import GuardConfig
from scanguard.slam.stream import ScanGuard
from tests.helpers import make_sequence, room_segments


def test_known_disagreements_in_standard_deviations():
    noise = OdometryNoise()  # 1 cm + 5 %/m; 0.5 deg + 5 %/rad + 1 deg/m
    odo = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.2, 0.1]])
    est = np.array(
        [
            [0.1, 0.0, 0.0],  # 10 cm slide at standstill: 10 sigma
            [1.0, 0.0, math.radians(3.0)],  # 3 deg off after 1 m: sigma 1.5 deg -> 2
            [0.5, 0.2, 0.1],  # agrees exactly
        ]
    )
    f = odometry_disagreement(est, odo, noise)
    np.testing.assert_allclose(f["odom_trans_z"], [10.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(f["odom_rot_z"], [0.0, 2.0, 0.0], atol=1e-9)
    np.testing.assert_array_equal(f["has_odometry"], [1.0, 1.0, 1.0])
    s_xy, s_th = odometry_sigmas(odo[1:2], noise)
    assert s_xy[0] == pytest.approx(0.06) and s_th[0] == pytest.approx(math.radians(1.5))


def test_translation_error_is_measured_in_the_odometry_frame():
    # a 10 cm error along the robot's own x axis after a 90 deg turn
    odo = np.array([[0.0, 0.0, math.pi / 2]])
    est = compose(odo, np.array([0.1, 0.0, 0.0]))
    f = odometry_disagreement(est, odo, OdometryNoise(rot_per_rad=0.0))
    assert f["odom_trans_z"][0] == pytest.approx(10.0)


def test_missing_odometry_is_masked_and_failed_matches_are_large():
    est = np.array([[0.3, 0.0, 0.0], [np.nan, np.nan, np.nan], [0.2, 0.0, 0.0]])
    odo = np.array([[np.nan, 0.0, 0.0], [0.2, 0.0, 0.0], [0.2, 0.0, 0.0]])
    f = odometry_disagreement(est, odo)
    np.testing.assert_array_equal(f["has_odometry"], [0.0, 1.0, 1.0])
    assert f["odom_trans_z"][0] == 0.0 and f["odom_rot_z"][0] == 0.0
    assert np.isinf(f["odom_trans_z"][1])  # a failed match where odometry exists
    none = odometry_disagreement(est, None)
    assert not none["has_odometry"].any() and not none["odom_trans_z"].any()
    x = metric_inputs(f, ["odom_trans_z", "odom_rot_z", "has_odometry"])
    assert np.isfinite(x).all() and x[1, 0] > 10.0  # log1p of a very large value
    assert x[0, 0] == 0.0 and x[2, 0] == 0.0  # no odometry / exact agreement


def test_store_odometry_increments_are_sensor_frame_odometry_steps(tmp_path):
    from scanguard.dataset import DatasetConfig
    from scanguard.dataset.labelling import label_sequence
    from scanguard.dataset.shards import write_sequence_file
    from scanguard.dataset.store import PairStore

    rng = np.random.default_rng(5)
    steps = np.column_stack(
        [rng.uniform(0.05, 0.1, 5), rng.uniform(-0.02, 0.02, 5), rng.uniform(-0.05, 0.05, 5)]
    )
    seq = make_sequence(room_segments(), steps, start=(-1.0, -0.5, 0.1), noise=0.0, name="odo")
    seq.laser_offset = np.array([0.2, 0.05, 0.1])
    drift = relative(seq.reference[:-1], seq.reference[1:]) + np.array([0.01, 0.0, 0.002])
    seq.odometry = np.vstack([[0.0, 0.0, 0.0], np.cumsum(drift, axis=0)])  # any odometry poses
    cfg = DatasetConfig(gmapping_score=False)
    rec = label_sequence(
        seq,
        environment="room",
        sequence="odo",
        split="train",
        matcher=get_matcher("icp"),
        matcher_name="icp",
        initial_guess="identity",
        labels=cfg.labels,
    )
    write_sequence_file(tmp_path / "odo.h5", rec)
    store = PairStore.open(tmp_path / "odo.h5")
    s = compose(seq.odometry, seq.laser_offset)
    np.testing.assert_allclose(store.records["odometry_increment"], relative(s[:-1], s[1:]))
    from scanguard.detect.features import store_features

    feats = store_features(store, np.arange(len(store)))
    assert (feats["has_odometry"] == 1.0).all() and np.isfinite(feats["odom_trans_z"]).all()


def _odometry_model(weight: float) -> FaultDetector:
    """A tiny hybrid whose fault margin is ``weight * odom_trans_z`` (after log1p), exactly."""
    names = list(ODOMETRY_METRIC_FEATURES)
    cfg = ModelConfig(
        preset="test",
        in_channels=2,
        input_size=32,
        widths=[4, 4, 4, 4, 4],
        dense=[4],
        conv_dropout=0.0,
        dense_dropout=0.0,
        metrics=names,
        metric_hidden=0,
    )
    model = build_model(cfg)
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        k = names.index("odom_trans_z")
        model.metric_net.weight[1, k] = weight  # type: ignore[index, union-attr]
    return FaultDetector(model, {"kind": "occupancy", "size": 32}, 0.5)


def test_detector_reads_the_odometry_given_and_masks_its_absence():
    rng = np.random.default_rng(2)
    steps = np.column_stack([rng.uniform(0.1, 0.15, 1), [0.0], [0.02]])
    seq = make_sequence(room_segments(), steps, start=(-1.0, -0.5, 0.1), noise=0.0)
    prev, cur = seq.scans
    match = get_matcher("icp")(cur.points(np.float64), prev.points(np.float64), None)
    det = _odometry_model(2.0)
    assert det.reads_odometry and det.odometry_noise == OdometryNoise()
    pose = np.asarray(match.pose)
    agree = det.fault_probability(prev, cur, pose, match, odometry=pose)
    off = det.fault_probability(prev, cur, pose, match, odometry=compose(pose, [0.3, 0, 0]))
    none = det.fault_probability(prev, cur, pose, match)
    assert agree == pytest.approx(0.5) and none == pytest.approx(0.5)
    # 0.3 m off, sigma = 1 cm + 5 % of ~0.43 m: z ~ 9.4, log1p ~ 2.34, margin ~ 4.7
    assert off > 0.98


def test_guard_hands_the_sensor_frame_odometry_increment_to_the_detector():
    rng = np.random.default_rng(3)
    steps = np.column_stack(
        [rng.uniform(0.05, 0.12, 6), rng.uniform(-0.03, 0.03, 6), rng.uniform(-0.04, 0.04, 6)]
    )
    seq = make_sequence(room_segments(), steps, start=(-2.0, -0.5, 0.1), noise=0.0)
    offset = np.array([0.3, 0.1, 0.2])
    seen: list = []
    det = _odometry_model(1.0)
    real = det.match_features

    def spy(previous, current, match, odometry=None):
        seen.append(None if odometry is None else np.asarray(odometry).copy())
        return real(previous, current, match, odometry)

    det.match_features = spy  # type: ignore[method-assign]
    guard = ScanGuard(det, get_matcher("icp-paper"), GuardConfig(), laser_offset=offset)
    for k, scan in enumerate(seq.scans):
        guard.step(scan, seq.reference[k])
    inc = relative(seq.reference[:-1], seq.reference[1:])
    expected = [robot_to_sensor_increment(i, offset) for i in inc]
    np.testing.assert_allclose(np.array(seen), np.array(expected), atol=1e-12)
    seen.clear()
    guard2 = ScanGuard(det, get_matcher("icp-paper"), GuardConfig())
    for scan in seq.scans:
        guard2.step(scan)
    assert seen and all(s is None for s in seen)


def test_training_hides_odometry_only_for_models_that_read_it():
    cfg = TrainConfig(odometry_dropout=0.3)
    odo = build_model(
        ModelConfig(
            in_channels=2,
            input_size=32,
            widths=[4] * 5,
            dense=[4],
            metrics=list(ODOMETRY_METRIC_FEATURES),
            metric_hidden=0,
        )
    )
    cols = odometry_columns(odo, cfg)
    assert cols is not None
    assert [ODOMETRY_METRIC_FEATURES[i] for i in cols.tolist()] == [
        "odom_trans_z",
        "odom_rot_z",
        "has_odometry",
    ]
    plain = build_model("tiny")
    assert odometry_columns(plain, cfg) is None
    assert odometry_columns(odo, TrainConfig(odometry_dropout=0.0)) is None


def test_metric_scaling_counts_hidden_odometry():
    """Data that always has odometry must not make a hidden pair an enormous input."""
    from scanguard.detect.train import train_images
    from scanguard.detect.train_config import ImageSet

    rng = np.random.default_rng(0)
    n = 64
    names = list(ODOMETRY_METRIC_FEATURES)
    metrics = rng.normal(0, 1, (n, len(names))).astype(np.float32)
    metrics[:, names.index("has_odometry")] = 1.0  # every training pair has odometry
    cfg = TrainConfig(
        model=ModelConfig(
            in_channels=2,
            input_size=32,
            widths=[4] * 5,
            dense=[4],
            metrics=names,
            metric_hidden=0,
        ),
        style={"kind": "occupancy", "size": 32},
        epochs=1,
        batch_size=16,
        odometry_dropout=0.3,
        threads=1,
    )
    images = rng.integers(0, 255, (n, 32, 32, 2), dtype=np.uint8)
    labels = rng.integers(0, 2, n)
    data = ImageSet(images, labels, metrics=metrics)
    res = train_images(cfg, data, data.subset(np.arange(0)))
    k = names.index("has_odometry")
    std = float(res.model.metric_std[k])
    assert 0.3 < std < 0.6  # sqrt(0.3 * 0.7) ~ 0.46, not the 1e-6 of a constant column
    hidden = (0.0 - float(res.model.metric_mean[k])) / std
    assert abs(hidden) < 5.0
