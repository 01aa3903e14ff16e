from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from scanguard.detect.checkpoint import load_checkpoint, save_checkpoint
from scanguard.detect.detector import FaultDetector, default_model_path, export_onnx
from scanguard.detect.render import RenderStyle, render_pairs
from scanguard.detect.train import train_images
from scanguard.detect.train_config import ImageSet, TrainConfig
from scanguard.errors import ModelError
from scanguard.scan import LaserScan
from tests.test_model import SMALL_SENSOR, synthetic_pairs

STYLE = {"kind": "occupancy", "size": 32}


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    prev, cur, est, lab = synthetic_pairs(160, seed=21)
    imgs = render_pairs(prev, cur, est, RenderStyle(**STYLE))
    data = ImageSet(imgs, lab)
    cfg = TrainConfig.from_dict(
        {"preset": "tiny", "style": STYLE, "epochs": 6, "batch_size": 16, "lr": 3e-3}
    )
    out = tmp_path_factory.mktemp("model")
    train_images(cfg, data.subset(np.arange(120)), data.subset(np.arange(120, 160)), out)
    return out / "model.pt"


def test_load_and_predict_pairs_consistently(trained: Path) -> None:
    det = FaultDetector.load(trained)
    assert det.style.kind == "occupancy" and det.style.size == 32
    assert 0.0 < det.threshold < 1.0
    prev, cur, est, lab = synthetic_pairs(40, seed=99)
    scans_p = [_scan_from_points(p) for p in prev]
    scans_c = [_scan_from_points(c) for c in cur]
    probs = det.predict_pairs(scans_p, scans_c, est)
    assert probs.shape == (40,)
    assert np.all((probs >= 0) & (probs <= 1))
    acc = np.mean((probs >= det.threshold) == (lab == 1))
    assert acc >= 0.8, acc
    one = det.fault_probability(scans_p[3], scans_c[3], est[3])
    assert one == pytest.approx(probs[3], abs=1e-6)
    assert det.is_fault(scans_p[3], scans_c[3], est[3]) == (probs[3] >= det.threshold)
    imgs = render_pairs(prev, cur, est, det.style)
    np.testing.assert_allclose(det.predict_images(imgs, batch_size=7), probs, atol=1e-6)
    # a directory containing model.pt works too
    assert FaultDetector.load(trained.parent).threshold == det.threshold


def _scan_from_points(points: np.ndarray) -> LaserScan:
    # rebuild a scan whose valid beams are exactly these points (one point per beam)
    ang = np.arctan2(points[:, 1], points[:, 0])
    rng = np.hypot(points[:, 0], points[:, 1])
    idx = np.round((ang - SMALL_SENSOR.angle_min) / SMALL_SENSOR.angle_increment).astype(int)
    ranges = np.full(SMALL_SENSOR.n_beams, np.inf, dtype=np.float32)
    ranges[idx % SMALL_SENSOR.n_beams] = rng
    return LaserScan.from_sensor(SMALL_SENSOR, 0.0, ranges)


def test_onnx_parity(trained: Path, tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    det = FaultDetector.load(trained)
    det_onnx = FaultDetector.load(trained, backend="onnx")
    rng = np.random.default_rng(0)
    imgs = (rng.random((37, 32, 32, 2)) < 0.05).astype(np.uint8) * 255
    p_t = det.predict_images(imgs)
    p_o = det_onnx.predict_images(imgs, batch_size=10)
    np.testing.assert_allclose(p_o, p_t, atol=1e-5)
    assert np.array_equal(p_o >= det.threshold, p_t >= det.threshold)
    out = export_onnx(det.model, tmp_path / "m.onnx")
    import onnx

    model = onnx.load(str(out))
    onnx.checker.check_model(model)
    assert [i.name for i in model.graph.input] == ["images"]


def test_corrupt_and_mismatched_files(trained: Path, tmp_path: Path) -> None:
    bad = tmp_path / "corrupt.pt"
    bad.write_bytes(trained.read_bytes()[:500])
    with pytest.raises(ModelError, match=r"corrupt\.pt"):
        FaultDetector.load(bad)
    junk = tmp_path / "junk.pt"
    junk.write_text("hello")
    with pytest.raises(ModelError, match=r"junk\.pt: not a readable"):
        FaultDetector.load(junk)
    with pytest.raises(ModelError, match=r"missing\.pt: model file not found"):
        FaultDetector.load(tmp_path / "missing.pt")
    ck = load_checkpoint(trained)
    ck["model_config"]["widths"] = [8, 8, 16, 16, 32]  # weights no longer fit
    mism = tmp_path / "mismatch.pt"
    save_checkpoint(ck, mism)
    with pytest.raises(ModelError, match=r"mismatch\.pt: weights do not match"):
        FaultDetector.load(mism)
    other = tmp_path / "other.pt"
    torch.save({"state_dict": {}}, other)
    with pytest.raises(ModelError, match=r"other\.pt: not a scanguard"):
        FaultDetector.load(other)
    with pytest.raises(ModelError, match="expected images"):
        FaultDetector.load(trained).predict_images(np.zeros((2, 16, 16, 2), np.uint8))


@pytest.mark.skipif(not default_model_path().exists(), reason="no shipped model yet")
def test_shipped_model_loads() -> None:
    det = FaultDetector.load()
    h, w, c = det.input_shape
    assert det.style.channels == c and det.style.size == h == w
    f = np.zeros((2, len(det.metric_names)), np.float32) if det.metric_names else None
    p = det.predict_images(np.zeros((2, h, w, c), np.uint8), features=f)
    assert p.shape == (2,)
    if det.metric_names:  # the shipped hybrid: a huge ICP residual must raise p(fault)
        base = {n: np.array([v]) for n, v in _GOOD_MATCH.items()}
        bad = {**base, "mean_residual": np.array([1.0]), "median_residual": np.array([0.8])}
        img = np.zeros((1, h, w, c), np.uint8)
        assert det.predict_images(img, features=bad)[0] > det.predict_images(img, features=base)[0]


@pytest.mark.skipif(not default_model_path().exists(), reason="no shipped model yet")
def test_shipped_model_onnx_parity() -> None:
    pytest.importorskip("onnxruntime")
    det = FaultDetector.load()
    det_onnx = FaultDetector.load(backend="onnx")
    h, w, c = det.input_shape
    rng = np.random.default_rng(7)
    imgs = (rng.random((24, h, w, c)) < 0.04).astype(np.uint8) * 255
    f = None
    if det.metric_names:
        f = {n: np.full(24, v) * rng.uniform(0.3, 3.0, 24) for n, v in _GOOD_MATCH.items()}
        f["converged"] = (rng.random(24) < 0.9).astype(float)
    p_t = det.predict_images(imgs, features=f)
    p_o = det_onnx.predict_images(imgs, batch_size=10, features=f)
    np.testing.assert_allclose(p_o, p_t, atol=1e-5)
    assert np.array_equal(p_o >= det.threshold, p_t >= det.threshold)


# Typical metrics of a good match in the simulated data (medians of normal pairs).
_GOOD_MATCH = {
    "mean_residual": 0.08,
    "median_residual": 0.04,
    "inlier_ratio": 0.6,
    "eig_min_per_inlier": 0.4,
    "gmapping_score_norm": 0.7,
    "iterations": 4.0,
    "converged": 1.0,
    # odometry input (read by models that take it): agrees with the match, odometry present
    "odom_trans_z": 0.5,
    "odom_rot_z": 0.5,
    "has_odometry": 1.0,
}


class _FakeMatch:
    """Just what a hybrid detector reads from a `MatchResult`."""

    def __init__(self, pose: np.ndarray, residual: float) -> None:
        self.pose = pose
        self.residual = residual

    def metrics(self) -> dict[str, float]:
        return {"mean_residual": self.residual, "inlier_ratio": 0.8, "iterations": 7.0}


@pytest.fixture(scope="module")
def hybrid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from scanguard.detect.checkpoint import make_checkpoint
    from scanguard.detect.model import build_model, get_preset

    cfg = get_preset("tiny").model_copy(
        update={"metrics": ["mean_residual", "inlier_ratio", "iterations"], "metric_hidden": 4}
    )
    torch.manual_seed(3)
    model = build_model(cfg)
    model.set_metric_scaling([-1.5, 0.5, 5.0], [0.5, 0.2, 3.0])
    with torch.no_grad():  # make the metric path matter: large weights on it
        model.metric_net[0].weight.mul_(20.0)  # type: ignore[index]
    ck = make_checkpoint(model, style=STYLE, threshold=0.5)
    return save_checkpoint(ck, tmp_path_factory.mktemp("hybrid") / "model.pt")


def test_hybrid_detector_reads_match_metrics(hybrid: Path, tmp_path: Path) -> None:
    from scanguard.detect.model import metric_inputs

    det = FaultDetector.load(hybrid)
    assert det.metric_names == ["mean_residual", "inlier_ratio", "iterations"]
    prev, cur, est, _ = synthetic_pairs(6, seed=5)
    sp, sc = _scan_from_points(prev[0]), _scan_from_points(cur[0])
    with pytest.raises(ModelError, match="match="):
        det.fault_probability(sp, sc, est[0])
    with pytest.raises(ModelError, match="features="):
        det.predict_images(det.render(sp, sc, est[0])[None])
    good = det.fault_probability(sp, sc, est[0], match=_FakeMatch(est[0], 0.01))
    bad = det.fault_probability(sp, sc, est[0], match=_FakeMatch(est[0], 2.0))
    assert good != pytest.approx(bad, abs=1e-3)  # the residual changes the answer
    # same number through the network called by hand
    img = torch.from_numpy(det.render(sp, sc, est[0])[None]).permute(0, 3, 1, 2).float() / 255
    feats = det.match_features(sp, sc, _FakeMatch(est[0], 2.0))
    met = torch.from_numpy(metric_inputs(feats, det.metric_names))
    assert bad == pytest.approx(float(det.model.fault_probability(img, met)[0]), abs=1e-6)
    # onnx parity with the two inputs
    pytest.importorskip("onnxruntime")
    rng = np.random.default_rng(1)
    imgs = (rng.random((9, 32, 32, 2)) < 0.05).astype(np.uint8) * 255
    m = {
        "mean_residual": rng.uniform(0.005, 1.0, 9),
        "inlier_ratio": rng.uniform(0, 1, 9),
        "iterations": rng.integers(1, 20, 9).astype(float),
    }
    p_t = det.predict_images(imgs, features=m)
    p_o = FaultDetector.load(hybrid, backend="onnx").predict_images(imgs, 4, features=m)
    np.testing.assert_allclose(p_o, p_t, atol=1e-5)
    import onnx

    onnx_model = onnx.load(str(export_onnx(det.model, tmp_path / "h.onnx")))
    assert [i.name for i in onnx_model.graph.input] == ["images", "metrics"]


_IMAGE_ONLY = default_model_path().with_name("image_only.pt")


@pytest.mark.skipif(not _IMAGE_ONLY.exists(), reason="no shipped image-only model")
def test_shipped_image_only_model() -> None:
    det = FaultDetector.load(_IMAGE_ONLY)
    assert det.metric_names == [] and det.style.kind == "multiscale"
    assert det.input_shape == (64, 64, 6)
    prev, cur, est, _ = synthetic_pairs(4, seed=8)
    sp, sc = _scan_from_points(prev[0]), _scan_from_points(cur[0])
    # image-only: no match needed, same number as the batched path
    one = det.fault_probability(sp, sc, est[0])
    assert one == pytest.approx(det.predict_pairs([sp], [sc], est[:1])[0], abs=1e-6)


def test_onnx_export_cached(trained: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ONNX export is made once per weights, reused, and made again when damaged."""
    pytest.importorskip("onnxruntime")
    import scanguard.detect.onnx_export as export_mod

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    calls: list[int] = []
    real = export_mod._export_bytes

    def counting(model: object) -> bytes:
        calls.append(1)
        return real(model)  # type: ignore[arg-type]

    monkeypatch.setattr(export_mod, "_export_bytes", counting)
    imgs = (np.random.default_rng(1).random((5, 32, 32, 2)) < 0.05).astype(np.uint8) * 255
    first = FaultDetector.load(trained, backend="onnx").predict_images(imgs)
    assert len(calls) == 1
    entries = list((tmp_path / "cache" / "scanguard" / "onnx").glob("*.onnx"))
    assert len(entries) == 1
    again = FaultDetector.load(trained, backend="onnx").predict_images(imgs)
    assert len(calls) == 1  # reused, not exported again
    np.testing.assert_array_equal(first, again)
    entries[0].write_bytes(b"not an onnx file")
    mended = FaultDetector.load(trained, backend="onnx").predict_images(imgs)
    assert len(calls) == 2
    np.testing.assert_array_equal(first, mended)
    assert entries[0].read_bytes() != b"not an onnx file"


def test_onnx_cache_unwritable(
    trained: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cache folder that cannot be written costs the export, nothing else."""
    pytest.importorskip("onnxruntime")
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would go")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    det = FaultDetector.load(trained, backend="onnx")
    imgs = np.zeros((2, 32, 32, 2), dtype=np.uint8)
    assert det.predict_images(imgs).shape == (2,)
    assert blocker.read_text().startswith("a file")
