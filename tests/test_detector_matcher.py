"""Per-matcher judges: a detector knows the matcher it was trained for and refuses others."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from scanguard.apps.run import run_recording
from scanguard.detect.checkpoint import LEGACY_MATCHER, make_checkpoint, save_checkpoint
from scanguard.detect.detector import FaultDetector
from scanguard.detect.train import store_matchers
from scanguard.errors import ModelError
from scanguard.matching import get_matcher
from scanguard.slam.config import RunConfig
from scanguard.slam.guard import GuardConfig
from scanguard.slam.judge import check_detector_matcher
from scanguard.slam.stream import ScanGuard
from tests.helpers import make_sequence, room_segments

STYLE = {"kind": "occupancy", "size": 32}
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def shipped() -> FaultDetector:
    return FaultDetector.load()


def _tiny_checkpoint(path: Path, matchers: list[str] | None = None) -> Path:
    from scanguard.detect.model import build_model, get_preset

    torch.manual_seed(0)
    model = build_model(get_preset("tiny"))
    ck = make_checkpoint(model, style=STYLE, threshold=0.5, matchers=matchers)
    return save_checkpoint(ck, path)


def test_shipped_model_was_trained_on_icp_paper(shipped: FaultDetector) -> None:
    # the default model covers the default back end's matcher, the paper's ICP
    assert shipped.checkpoint.get("matchers", [LEGACY_MATCHER]) == ["icp-paper"]
    assert shipped.matchers == (LEGACY_MATCHER,) == ("icp-paper",)
    assert shipped.check_matcher("icp-paper") is True


def test_other_matcher_is_refused_with_one_line(shipped: FaultDetector) -> None:
    with pytest.raises(ModelError) as info:
        shipped.check_matcher("plicp")
    msg = str(info.value)
    assert "\n" not in msg
    assert "trained on icp-paper matches, not plicp" in msg
    assert "--allow-other-matcher" in msg and "uncalibrated" in msg


def test_other_matcher_allowed_warns(
    shipped: FaultDetector, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="scanguard.detect.detector"):
        assert shipped.check_matcher("plicp", allow_other=True) is False
    assert any("uncalibrated" in r.getMessage() for r in caplog.records)


def test_checkpoint_records_matchers(tmp_path: Path) -> None:
    p = _tiny_checkpoint(tmp_path / "m.pt", matchers=["plicp", "icp", "plicp"])
    det = FaultDetector.load(p)
    assert det.matchers == ("icp", "plicp")
    assert det.check_matcher("plicp") and det.check_matcher("icp")
    with pytest.raises(ModelError, match="trained on icp or plicp matches, not icp-paper"):
        det.check_matcher("icp-paper")
    # without the field: the legacy default
    assert FaultDetector.load(_tiny_checkpoint(tmp_path / "old.pt")).matchers == ("icp-paper",)


@pytest.mark.parametrize("bad", [[], "plicp", [3], [""]])
def test_malformed_matchers_field_is_refused(tmp_path: Path, bad: object) -> None:
    p = _tiny_checkpoint(tmp_path / "m.pt")
    ck = torch.load(p, weights_only=True)
    ck["matchers"] = bad
    save_checkpoint(ck, p)
    with pytest.raises(ModelError, match="'matchers'"):
        FaultDetector.load(p)


def test_store_matchers_reads_the_pair_files() -> None:
    store = SimpleNamespace(
        records={"file": np.array([0, 0, 1, 1, 2], dtype=np.int32)},
        file_attrs=[{"matcher": "plicp"}, {"matcher": "icp-paper"}, {}],
    )
    assert store_matchers(store, [0, 1]) == ["plicp"]
    assert store_matchers(store, [0, 2, 3]) == ["icp-paper", "plicp"]
    assert store_matchers(store, [4]) == []


def test_guard_checks_its_matcher(shipped: FaultDetector, caplog: pytest.LogCaptureFixture) -> None:
    cfg = GuardConfig(update_map=False)
    ScanGuard(shipped, get_matcher("icp-paper"), cfg)
    with pytest.raises(ModelError, match="not plicp"):
        ScanGuard(shipped, get_matcher("plicp"), cfg)
    ScanGuard(shipped, get_matcher("plicp"), cfg, allow_other_matcher=True)
    # a matcher without a name cannot be checked: a warning, not a refusal
    with caplog.at_level(logging.WARNING, logger="scanguard.slam.guard"):
        ScanGuard(shipped, lambda s, t, i=None: None, cfg)
    assert any("has no name" in r.getMessage() for r in caplog.records)
    # a detector that does not know its matchers is not checked
    assert check_detector_matcher(object(), "plicp") is True


@pytest.fixture(scope="module")
def room():
    return make_sequence(room_segments(), np.tile([0.06, 0.01, 0.02], (3, 1)))


def test_run_refuses_other_matcher_before_any_work(
    shipped: FaultDetector, room, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    cfg = RunConfig(backend="frontend", matcher="plicp")
    with pytest.raises(ModelError, match="not plicp"):
        run_recording(room, shipped, out, config=cfg)
    assert not out.exists()
    # a matcher object is checked by its name
    with pytest.raises(ModelError, match="not icp"):
        run_recording(
            room, shipped, out, config=RunConfig(backend="frontend"), matcher=get_matcher("icp")
        )
    assert not out.exists()


def test_run_with_allowed_other_matcher(shipped: FaultDetector, room, tmp_path: Path) -> None:
    cfg = RunConfig(backend="frontend", matcher="plicp", allow_other_matcher=True)
    res = run_recording(room, shipped, tmp_path / "run", config=cfg)
    assert res.matcher == "plicp" and res.n_scans == len(room)


def test_laser_odometry_config_allows_its_matcher() -> None:
    cfg = RunConfig.from_yaml(ROOT / "configs" / "run_laser_odometry.yaml")
    assert cfg.matcher == "plicp" and cfg.allow_other_matcher is True
    assert RunConfig().allow_other_matcher is False


def test_cli_flag_sets_allow_other_matcher() -> None:
    from scanguard.apps.config_merge import run_config

    assert run_config(None, matcher="plicp").allow_other_matcher is False
    assert run_config(None, matcher="plicp", allow_other_matcher=True).allow_other_matcher
    # the flag's absence does not switch off what a config file turned on
    laser = str(ROOT / "configs" / "run_laser_odometry.yaml")
    assert run_config(laser).allow_other_matcher is True


def test_training_records_the_dataset_matcher(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from scanguard.dataset import build_dataset
    from scanguard.dataset import tasks as build_mod
    from scanguard.detect.train import train
    from scanguard.detect.train_config import TrainConfig
    from tests.test_dataset import fake_simulate, tiny_config

    monkeypatch.setattr(build_mod, "_simulate", fake_simulate)
    build_dataset(tiny_config(matcher="plicp"), tmp_path / "data", progress=False)
    cfg = TrainConfig.from_dict(
        {"preset": "tiny", "style": STYLE, "epochs": 1, "batch_size": 8, "seed": 0, "threads": 1}
    )
    res = train(cfg, tmp_path / "data", tmp_path / "model")
    assert res.checkpoint["matchers"] == ["plicp"]
    assert FaultDetector.load(tmp_path / "model").matchers == ("plicp",)


def test_each_matcher_loads_its_own_shipped_model(tmp_path: Path, monkeypatch) -> None:
    import scanguard.apps.run_baseline as run_mod
    import scanguard.detect.detector as detector_mod

    pkg = tmp_path / "scanguard"
    (pkg / "models").mkdir(parents=True)
    _tiny_checkpoint(pkg / "models" / "default.pt", ["icp-paper"])
    _tiny_checkpoint(pkg / "models" / "plicp.pt", ["plicp"])
    (pkg / "models" / "baseline-plicp.json").write_text("{}")
    fake = SimpleNamespace(files=lambda name: pkg)
    monkeypatch.setattr(detector_mod, "resources", fake)
    monkeypatch.setattr("importlib.resources.files", lambda name: pkg)
    assert FaultDetector.load(matcher="plicp").matchers == ("plicp",)
    assert FaultDetector.load(matcher="icp-paper").matchers == ("icp-paper",)
    # no model of its own: the default one, which then refuses the matcher
    icp = FaultDetector.load(matcher="icp")
    assert icp.matchers == ("icp-paper",)
    with pytest.raises(ModelError, match="not icp"):
        icp.check_matcher("icp")
    assert run_mod.shipped_baseline_path("plicp").name == "baseline-plicp.json"
    assert run_mod.shipped_baseline_path("icp").name == "baseline.json"
    assert run_mod.shipped_baseline_path(None).name == "baseline.json"
