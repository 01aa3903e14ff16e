from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from scanguard.detect.render import RenderStyle, render_pairs
from scanguard.detect.train import train_images
from scanguard.detect.train_config import ImageSet, TrainConfig
from scanguard.detect.train_epoch import predict_proba
from scanguard.errors import ConfigError
from scanguard.scoring import metric_threshold as choose_threshold
from tests.test_model import synthetic_pairs

STYLE = {"kind": "occupancy", "size": 32}


def _images(n: int, seed: int) -> ImageSet:
    prev, cur, est, lab = synthetic_pairs(n, seed=seed)
    imgs = render_pairs(prev, cur, est, RenderStyle(**STYLE))
    env = np.array(["room"] * n)
    seq = np.array([f"s{seed}"] * n)
    return ImageSet(imgs, lab, env, seq)


@pytest.fixture(scope="module")
def data() -> tuple[ImageSet, ImageSet]:
    return _images(320, seed=10), _images(120, seed=11)


def _config(**kw: object) -> TrainConfig:
    base = {
        "preset": "tiny",
        "style": STYLE,
        "epochs": 6,
        "batch_size": 16,
        "patience": 0,
        "seed": 0,
        "lr": 3e-3,
        "threads": 2,
    }
    base.update(kw)
    return TrainConfig.from_dict(base)


def test_tiny_training_beats_chance_and_writes_outputs(
    data: tuple[ImageSet, ImageSet], tmp_path: Path
) -> None:
    tr, va = data
    res = train_images(_config(), tr, va, tmp_path, label_thresholds={"fault_displacement": 0.1})
    p = predict_proba(res.model, va.images)
    acc = float(np.mean((p >= res.checkpoint["threshold"]) == (va.labels == 1)))
    # balanced classes: chance is 0.5
    assert acc >= 0.85, acc
    assert res.history[-1]["train_loss"] < res.history[0]["train_loss"]
    for name in ("model.pt", "config.yaml", "history.json", "curves.png"):
        assert (tmp_path / name).is_file(), name
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".")]  # no temp leftovers
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["model"]["preset"] == "tiny" and cfg["style"] == STYLE
    hist = json.loads((tmp_path / "history.json").read_text())
    assert len(hist) == 6 and {"val_loss", "train_accuracy"} <= set(hist[0])
    ck = torch.load(tmp_path / "model.pt", weights_only=True)
    assert ck["style"] == STYLE
    assert ck["label_thresholds"] == {"fault_displacement": 0.1}
    assert ck["train_config"]["epochs"] == 6
    best = ck["info"]["best_epoch"]
    assert hist[best - 1]["val_accuracy"] == max(h["val_accuracy"] for h in hist)


def test_training_is_reproducible(data: tuple[ImageSet, ImageSet]) -> None:
    tr, va = data
    small_tr, small_va = tr.subset(np.arange(96)), va.subset(np.arange(32))
    a = train_images(_config(epochs=2), small_tr, small_va)
    b = train_images(_config(epochs=2), small_tr, small_va)
    for k, v in a.checkpoint["state_dict"].items():
        assert torch.equal(v, b.checkpoint["state_dict"][k]), k
    assert a.history == [
        {**h, "images_per_s": a.history[i]["images_per_s"]} for i, h in enumerate(b.history)
    ]


def test_wrong_image_shape_is_rejected(data: tuple[ImageSet, ImageSet]) -> None:
    tr, va = data
    with pytest.raises(ConfigError, match="expects 64x64x2"):
        train_images(_config(preset="compact", style=None), tr, va)


def test_choose_threshold_known_answer() -> None:
    y = np.array([0, 0, 0, 1, 1, 1])
    p = np.array([0.1, 0.2, 0.7, 0.8, 0.9, 0.95])
    # 0.5 misclassifies the 0.7; the best cut lies between 0.7 and 0.8
    assert choose_threshold(y, p) == pytest.approx(0.75)
    assert choose_threshold(y, p, "fixed") == 0.5
    assert choose_threshold(np.array([1, 1]), np.array([0.2, 0.3])) == 0.5


def test_hybrid_model_learns_from_the_metrics(data: tuple[ImageSet, ImageSet]) -> None:
    """Blank images: only the metric input carries the label, so accuracy >> chance proves
    the metric path is trained and standardised (raw values are far from unit scale)."""
    from scanguard.detect.model import get_preset

    tr, va = data
    rng = np.random.default_rng(5)

    def with_metrics(d: ImageSet) -> ImageSet:
        met = np.column_stack(
            [1000.0 + 40.0 * d.labels + rng.normal(0, 10, len(d)), rng.normal(0, 1, len(d))]
        ).astype(np.float32)
        return ImageSet(np.zeros_like(d.images), d.labels, metrics=met)

    model = get_preset("tiny").model_copy(update={"metrics": ["a", "b"], "metric_hidden": 8})
    cfg = _config(model=model, epochs=4)
    with pytest.raises(ConfigError, match="needs the metrics"):
        train_images(cfg, tr, va)
    mtr, mva = with_metrics(tr), with_metrics(va)
    res = train_images(cfg, mtr, mva)
    assert float(res.model.metric_mean[0]) == pytest.approx(float(mtr.metrics[:, 0].mean()))
    p = predict_proba(res.model, mva.images, metrics=mva.metrics)
    acc = float(np.mean((p >= res.checkpoint["threshold"]) == (mva.labels == 1)))
    assert acc >= 0.9, acc


def test_schedules_and_balanced_sampling(data: tuple[ImageSet, ImageSet]) -> None:
    from scanguard.detect.model import build_model
    from scanguard.detect.train_epoch import make_schedule

    opt = torch.optim.Adam(build_model("tiny").parameters(), lr=1e-2)
    cfg = _config(schedule="cosine", epochs=2, lr=1e-2)
    sched = make_schedule(opt, cfg, steps_per_epoch=5)
    assert sched is not None
    lrs = []
    for _ in range(10):
        opt.step()
        sched.step()
        lrs.append(opt.param_groups[0]["lr"])
    assert lrs[4] == pytest.approx(5e-3) and lrs[-1] == pytest.approx(0.0, abs=1e-12)
    assert make_schedule(opt, _config(), 5) is None
    # balanced sampling on a 1:9 set: each class gets about half of the draws
    from scanguard.detect.train_epoch import epoch_order

    labels = np.array([1] * 100 + [0] * 900, dtype=np.int64)
    gen = torch.Generator().manual_seed(0)
    order = epoch_order(labels, True, gen)
    assert len(order) == 1000 and 0.45 < labels[order].mean() < 0.55
    plain = epoch_order(labels, False, gen)
    assert sorted(plain.tolist()) == list(range(1000))
