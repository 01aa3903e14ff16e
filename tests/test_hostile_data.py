"""Hostile-input regressions of the dataset store and the fail-safe models (issue 11).

Items covered (numbers of the issue): 2, 3, 4, 5, 8 (labels), 9, 10, 12, 24, 26, 30, 31 and
"evaluate on a store of recordings only". Recordings are tiny corrected CARMEN logs written
here from synthetic scans; simulated builds use a synthetic room instead of the simulator.
"""

from __future__ import annotations

import fcntl
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from scanguard.dataset import (
    DatasetConfig,
    PairStore,
    build_dataset,
    build_from_recording,
    label_sequence,
    tasks,
    write_sequence_file,
)
from scanguard.dataset import build as build_mod
from scanguard.dataset.build import build_from_recordings
from scanguard.dataset.manifest import BUILD_LOCK, MANIFEST_LOCK, update_manifest
from scanguard.dataset.planning import PlannedSequence
from scanguard.detect.checkpoint import make_checkpoint, save_checkpoint
from scanguard.detect.detector import FaultDetector
from scanguard.detect.model import build_model, get_preset
from scanguard.detect.train import train_images
from scanguard.detect.train_config import ImageSet, TrainConfig
from scanguard.errors import ConfigError, InputError, ModelError
from scanguard.matching import get_matcher
from scanguard.pairs.labels import AMBIGUOUS, FAULT, LabelConfig, assign_labels, non_finite_errors
from scanguard.scan import SensorInfo
from scanguard.slam.guard import GuardConfig
from scanguard.slam.stream import ScanGuard
from tests.helpers import make_sequence, room_segments

# a SICK LMS as CARMEN's FLASER lines describe it: 181 beams over 180 degrees
FLASER = SensorInfo(
    name="sick",
    n_beams=181,
    angle_min=-math.pi / 2,
    angle_increment=math.pi / 180,
    range_min=0.01,
    range_max=80.0,
    rate_hz=5.0,
)
CFG = DatasetConfig(gmapping_score=False)
STYLE = {"kind": "occupancy", "size": 32}


def room_sequence(seed: int, n: int = 6, name: str = "room", sensor: SensorInfo = FLASER):
    rng = np.random.default_rng(seed)
    steps = np.column_stack(
        [
            rng.uniform(0.05, 0.15, n - 1),
            rng.uniform(-0.03, 0.03, n - 1),
            rng.uniform(-0.05, 0.05, n - 1),
        ]
    )
    return make_sequence(
        room_segments(),
        steps,
        start=(-1.0, -0.5, 0.1),
        sensor=sensor,
        noise=0.005,
        seed=seed,
        name=name,
    )


def write_corrected_log(path: Path, seed: int, n: int = 6) -> Path:
    """A SLAM-corrected CARMEN log (poses = reference) of a synthetic room walk."""
    seq = room_sequence(seed, n)
    lines = []
    for i, (scan, (x, y, th)) in enumerate(zip(seq.scans, seq.reference, strict=True)):
        ranges = " ".join(f"{v:.3f}" for v in scan.ranges)
        pose = f"{x:.6f} {y:.6f} {th:.6f}"
        t = 1000.0 + 0.2 * i
        lines.append(f"FLASER 181 {ranges} {pose} {pose} {t:.3f} host {t:.3f}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def fake_simulate(item: PlannedSequence):
    return room_sequence(item.seed, n=6, name=item.sequence)


def sim_config(**kw: Any) -> DatasetConfig:
    data: dict[str, Any] = {
        "name": "tiny",
        "matcher": "icp-paper",
        "gmapping_score": False,
        "splits": {"val_sequences": 1, "test_sequences": 1, "seed": 3},
        "environments": [
            {"name": "lobby", "scenario": "lobby", "sequences": 3, "duration": 1.0, "seed": 0},
        ],
    }
    data.update(kw)
    return DatasetConfig.from_dict(data)


def manifest(d: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((d / "manifest.json").read_text())
    return data


def sequences(d: Path) -> list[str]:
    return [e["sequence"] for e in manifest(d)["sequences"]]


@pytest.fixture
def sim(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tasks, "_simulate", fake_simulate)


# --- item 4: content identity ---------------------------------------------------------------


def test_two_recordings_with_one_name_are_both_built(tmp_path: Path) -> None:
    a = write_corrected_log(tmp_path / "a" / "walk-corrected.log", seed=1)
    b = write_corrected_log(tmp_path / "b" / "walk-corrected.log", seed=2)
    out = tmp_path / "store"
    first = build_from_recording(a, out, CFG, progress=False)
    second = build_from_recording(b, out, CFG, progress=False)
    assert first.built == ["walk-corrected"]
    assert len(second.built) == 1 and second.built[0].startswith("walk-corrected_")
    store = PairStore.open(out)
    assert len(store) == 10 and len(set(store.records["sequence"].tolist())) == 2
    # the same content again, from a third place, is recognised (not built a third time)
    c = tmp_path / "c" / "walk-corrected.log"
    c.parent.mkdir()
    shutil.copyfile(b, c)
    again = build_from_recording(c, out, CFG, progress=False)
    assert again.built == [] and again.skipped == second.built


def test_changed_recording_is_rebuilt_without_stale_pairs(tmp_path: Path) -> None:
    log_path = write_corrected_log(tmp_path / "walk-corrected.log", seed=1, n=6)
    out = tmp_path / "store"
    build_from_recording(log_path, out, CFG, progress=False)
    assert len(PairStore.open(out)) == 5
    write_corrected_log(log_path, seed=3, n=8)  # the same file, re-recorded
    s = build_from_recording(log_path, out, CFG, progress=False)
    assert s.built == ["walk-corrected"] and s.skipped == []
    store = PairStore.open(out)
    assert len(store) == 7 and sequences(out) == ["walk-corrected"]
    assert len(list((out / "sequences").glob("*.h5"))) == 1
    # other settings for the same file are still refused (not silently mixed)
    with pytest.raises(ConfigError, match="other settings"):
        build_from_recording(log_path, out, CFG, progress=False, max_scans=4)


def test_recording_topics_reach_the_reader(tmp_path: Path) -> None:
    log_path = write_corrected_log(tmp_path / "walk-corrected.log", seed=1)
    out = tmp_path / "store"
    s = build_from_recording(log_path, out, CFG, progress=False, scan_topic="FLASER")
    assert s.built == ["walk-corrected"]
    with pytest.raises(InputError, match="RLASER"):
        build_from_recording(log_path, tmp_path / "other", CFG, progress=False, scan_topic="RLASER")
    assert manifest(tmp_path / "other")["pending"] == []


# --- item 2: manifest updates under a lock --------------------------------------------------


_CHILD = """
import sys
from scanguard.dataset import DatasetConfig, build_from_recording
build_from_recording(sys.argv[1], sys.argv[2], DatasetConfig(gmapping_score=False), progress=False)
"""


def test_concurrent_recording_builds_keep_both(tmp_path: Path) -> None:
    a = write_corrected_log(tmp_path / "one-corrected.log", seed=1)
    b = write_corrected_log(tmp_path / "two-corrected.log", seed=2)
    out = tmp_path / "store"
    # two separate processes, started together, as two shells running `dataset build -r`
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _CHILD, str(p), str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        for p in (a, b)
    ]
    for p in procs:
        output, _ = p.communicate(timeout=120)
        assert p.returncode == 0, output.decode(errors="replace")
    assert sorted(sequences(out)) == ["one-corrected", "two-corrected"]
    assert manifest(out)["complete"] is True and manifest(out)["pending"] == []
    assert len(PairStore.open(out)) == 10


def test_manifest_updates_from_many_threads_are_all_kept(tmp_path: Path) -> None:
    out = tmp_path / "store"

    def add(k: int) -> None:
        for j in range(5):
            entry = {"file": f"sequences/s{k}_{j}.h5", "sequence": f"s{k}_{j}"}
            update_manifest(out, lambda m, e=entry: {**m, "sequences": [*m["sequences"], e]})

    threads = [threading.Thread(target=add, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(sequences(out)) == 30


# --- items 3 and 5: refused builds, mixed builds ----------------------------------------------


def test_refused_build_keeps_config_yaml(tmp_path: Path, sim: None) -> None:
    out = tmp_path / "d"
    build_dataset(sim_config(), out, progress=False)
    before = (out / "config.yaml").read_text()
    with pytest.raises(ConfigError, match="another config"):
        build_dataset(sim_config(labels={"fault_displacement": 0.2}), out, progress=False)
    assert (out / "config.yaml").read_text() == before


def test_resumed_simulated_build_keeps_recordings(tmp_path: Path, sim: None) -> None:
    out = tmp_path / "d"
    build_dataset(sim_config(), out, progress=False, max_sequences=1)
    rec = write_corrected_log(tmp_path / "walk-corrected.log", seed=4)
    build_from_recording(rec, out, CFG, progress=False)
    s = build_dataset(sim_config(), out, progress=False)
    assert len(s.built) == 2 and len(s.skipped) == 1
    assert sequences(out) == ["lobby_00", "lobby_01", "lobby_02", "walk-corrected"]
    assert manifest(out)["complete"] is True
    assert "walk-corrected" in set(PairStore.open(out).records["sequence"].tolist())


# --- items 10 and 31: an honest complete flag, a full summary --------------------------------


def test_interrupted_multi_recording_build_is_incomplete(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    logs = [write_corrected_log(tmp_path / f"r{k}-corrected.log", seed=k) for k in range(3)]
    out = tmp_path / "store"
    real = build_mod.build_recording
    calls = {"n": 0}

    def interrupted(*args: Any, **kw: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kw)

    monkeypatch.setattr(build_mod, "build_recording", interrupted)
    with pytest.raises(KeyboardInterrupt):
        build_from_recordings(logs, out, CFG, progress=False)
    m = manifest(out)
    assert m["complete"] is False and sequences(out) == ["r0-corrected"]
    assert len(m["pending"]) == 2
    with caplog.at_level(logging.WARNING):
        store = PairStore.open(out)
    assert store.incomplete and "incomplete dataset build" in caplog.text
    # train refuses it unless told otherwise
    cfg = TrainConfig.from_dict({"preset": "tiny", "style": STYLE, "epochs": 1})
    with pytest.raises(ConfigError, match="incomplete dataset build"):
        from scanguard.detect.train import train

        train(cfg, out, tmp_path / "model")
    allowed = cfg.model_copy(update={"allow_incomplete": True})
    with pytest.raises(ConfigError, match="training set is empty"):  # past the check
        train(allowed, out, tmp_path / "model")
    assert not (tmp_path / "model").exists()
    # resuming builds the rest; the summary counts every recording of the call
    monkeypatch.setattr(build_mod, "build_recording", real)
    s = build_from_recordings(logs, out, CFG, progress=False)
    assert len(s.built) == 2 and s.skipped == ["r0-corrected"] and s.complete
    assert manifest(out)["complete"] is True and manifest(out)["pending"] == []
    assert not PairStore.open(out).incomplete
    again = build_from_recordings(logs, out, CFG, progress=False)
    assert again.built == [] and len(again.skipped) == 3


def test_interrupted_simulated_build_is_incomplete(tmp_path: Path, sim: None) -> None:
    out = tmp_path / "d"
    build_dataset(sim_config(), out, progress=False, max_sequences=1)
    m = manifest(out)
    assert m["complete"] is False and [x["sequence"] for x in m["pending"]] == [
        "lobby_01",
        "lobby_02",
    ]
    assert PairStore.open(out).incomplete


def test_failing_recording_is_not_left_pending(tmp_path: Path) -> None:
    bag = tmp_path / "nothing.log"
    bag.write_text("ODOM 0 0 0 0 0 0 1.0 host 1.0\n")
    out = tmp_path / "store"
    with pytest.raises(InputError):
        build_from_recording(bag, out, CFG, progress=False)
    assert manifest(out)["pending"] == [] and manifest(out)["complete"] is True


# --- items 12 and 30: temporary files, corrupt shards -----------------------------------------


def test_resume_cleans_temporary_files(tmp_path: Path, sim: None) -> None:
    out = tmp_path / "d"
    build_dataset(sim_config(), out, progress=False, max_sequences=1)
    junk = [
        out / "sequences" / ".lobby_01.h5.sg99999-abcdefgh.h5",
        out / "sequences" / "lobby_02.h5.tmp",
        out / ".manifest.json.sg99999-abcdefgh.json",
    ]
    for j in junk:
        j.write_bytes(b"\x89HDF partial")
    # while another build runs here, its temporary files are left alone
    fd = os.open(out / BUILD_LOCK, os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_SH)
    try:
        build_dataset(sim_config(), out, progress=False, max_sequences=0)
        assert all(j.exists() for j in junk)
    finally:
        os.close(fd)
    build_dataset(sim_config(), out, progress=False)
    assert not any(j.exists() for j in junk)
    assert (out / BUILD_LOCK).exists() and (out / MANIFEST_LOCK).exists()
    assert sorted(p.name for p in (out / "sequences").iterdir()) == [
        "lobby_00.h5",
        "lobby_01.h5",
        "lobby_02.h5",
    ]


def test_corrupt_shard_is_reported_and_rebuilt(
    tmp_path: Path, sim: None, caplog: pytest.LogCaptureFixture
) -> None:
    full = build_dataset(sim_config(), tmp_path / "full", progress=False)
    out = tmp_path / "d"
    build_dataset(sim_config(), out, progress=False, max_sequences=2)
    shard = out / "sequences" / "lobby_00.h5"
    shard.write_bytes(shard.read_bytes()[:900])  # truncated by a crash
    with caplog.at_level(logging.WARNING):
        s = build_dataset(sim_config(), out, progress=False)
    assert "CORRUPT" in caplog.text and "fingerprint None" not in caplog.text
    assert sorted(s.built) == ["lobby_00", "lobby_02"]
    assert s.entries == full.entries
    # the same for a recording's shard
    rec = write_corrected_log(tmp_path / "walk-corrected.log", seed=5)
    build_from_recording(rec, out, CFG, progress=False)
    (out / "sequences" / "walk-corrected.h5").write_bytes(b"garbage")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        again = build_from_recording(rec, out, CFG, progress=False)
    assert again.built == ["walk-corrected"] and "CORRUPT" in caplog.text
    assert len(PairStore.open(out)) == 20


# --- item 26: malformed manifests -------------------------------------------------------------


@pytest.mark.parametrize(
    ("sequences_value", "message"),
    [
        ("sequences/a.h5", "'sequences' is a string, not a list"),
        ({"file": "a.h5"}, "'sequences' is a object, not a list"),
        ([3], r"sequences\[0\] is a number"),
        ([{"file": "../../etc/passwd"}], "outside the directory"),
    ],
)
def test_malformed_manifest_is_one_line_naming_it(
    tmp_path: Path, sequences_value: Any, message: str
) -> None:
    (tmp_path / "manifest.json").write_text(
        json.dumps({"format": "scanguard-pairs", "sequences": sequences_value})
    )
    with pytest.raises(InputError, match=message) as err:
        PairStore.open(tmp_path)
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(tmp_path / "manifest.json"))


def test_cli_stats_on_malformed_manifest(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from scanguard.cli import app

    (tmp_path / "manifest.json").write_text(
        json.dumps({"format": "scanguard-pairs", "sequences": "x"})
    )
    res = CliRunner().invoke(app, ["dataset", "stats", str(tmp_path)])
    assert res.exit_code == 1 and "not a list" in res.output
    assert "Traceback" not in res.output


# --- item 8: labels are never computed from non-finite errors ---------------------------------


def test_non_finite_errors_are_ambiguous_never_faults() -> None:
    t = np.array([0.01, np.nan, 0.3, np.inf, 0.3])
    r = np.array([0.0, 0.0, 0.0, 0.0, np.nan])
    d = np.array([0.01, np.nan, 0.3, 0.01, 0.3])
    lab = assign_labels(t, r, d, LabelConfig())
    assert lab.tolist() == [0, AMBIGUOUS, FAULT, AMBIGUOUS, AMBIGUOUS]
    assert non_finite_errors(t, r, d).tolist() == [False, True, False, True, True]
    # a match known to have failed (no finite estimate) is a fault, said explicitly
    failed = np.array([False, True, False, False, False])
    lab = assign_labels(t, r, d, LabelConfig(), diverged=failed)
    assert lab.tolist() == [0, FAULT, FAULT, AMBIGUOUS, AMBIGUOUS]


def test_nan_reference_pose_labels_are_reported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    seq = room_sequence(1, n=6)
    seq.reference[3] = np.nan  # pairs (2, 3) and (3, 4) have no answer
    with caplog.at_level(logging.WARNING):
        rec = label_sequence(
            seq,
            environment="room",
            sequence="room",
            split="heldout",
            matcher=get_matcher("icp-paper"),
            matcher_name="icp-paper",
            initial_guess="identity",
            labels=LabelConfig(),
            gmapping=False,
        )
    assert rec.pairs["label"][2] == AMBIGUOUS and rec.pairs["label"][3] == AMBIGUOUS
    assert rec.meta["non_finite_pairs"] == 2 and "non-finite errors" in caplog.text
    seq.reference[:] = np.nan
    with pytest.raises(InputError, match="no pair has a finite error"):
        label_sequence(
            seq,
            environment="room",
            sequence="room",
            split="heldout",
            matcher=get_matcher("icp-paper"),
            matcher_name="icp-paper",
            initial_guess="identity",
            labels=LabelConfig(),
            gmapping=False,
        )
    # a file written before the fix (NaN errors labelled fault) is flagged on opening
    rec.pairs["label"][2] = FAULT
    path = write_sequence_file(tmp_path / "old.h5", rec)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        PairStore.open(path)
    assert "non-finite errors" in caplog.text


# --- item 9 and fail-safe models --------------------------------------------------------------


def _images(n: int, seed: int) -> ImageSet:
    rng = np.random.default_rng(seed)
    return ImageSet(rng.integers(0, 255, (n, 32, 32, 2), dtype=np.uint8), np.arange(n) % 2)


def test_diverging_training_saves_nothing(tmp_path: Path) -> None:
    cfg = TrainConfig.from_dict(
        {"preset": "tiny", "style": STYLE, "epochs": 2, "lr": 1e30, "augment": False}
    )
    out = tmp_path / "run"
    with pytest.raises(ConfigError, match="training diverged") as err:
        train_images(cfg, _images(64, 0), _images(16, 1), out)
    assert "\n" not in str(err.value) and str(out) in str(err.value)
    assert not out.exists()


def _checkpoint(tmp_path: Path, threshold: float, poison: bool = False) -> Path:
    model = build_model(get_preset("tiny"))
    if poison:
        with torch.no_grad():
            next(model.parameters()).view(-1)[0] = float("nan")
    ckpt = make_checkpoint(model, style=STYLE, threshold=0.5)
    ckpt["threshold"] = threshold
    return save_checkpoint(ckpt, tmp_path / f"model-{threshold}-{poison}.pt")


@pytest.mark.parametrize("threshold", [float("nan"), 5.0, -0.1, float("inf")])
def test_checkpoint_threshold_outside_unit_interval_is_refused(
    tmp_path: Path, threshold: float
) -> None:
    path = _checkpoint(tmp_path, threshold)
    with pytest.raises(ModelError, match=r"not a probability in \[0, 1\]") as err:
        FaultDetector.load(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_checkpoint_with_non_finite_weights_is_refused(tmp_path: Path) -> None:
    path = _checkpoint(tmp_path, 0.5, poison=True)
    with pytest.raises(ModelError, match="non-finite weights"):
        FaultDetector.load(path)
    assert FaultDetector.load(_checkpoint(tmp_path, 1.0)).threshold == 1.0


class NaNDetector:
    """A detector whose model outputs NaN (a diverged checkpoint)."""

    threshold = 0.5

    def fault_probability(self, previous: Any, current: Any, pose: Any) -> float:
        return float("nan")


def test_guard_treats_nan_probability_as_fault_and_says_so_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    seq = room_sequence(7, n=5)
    guard = ScanGuard(NaNDetector(), get_matcher("icp"), GuardConfig(update_map=False))
    with caplog.at_level(logging.WARNING, logger="scanguard.slam.guard"):
        decisions = [guard.step(s) for s in seq.scans]
    assert [d.reason for d in decisions[1:]] == ["rejected_cnn"] * 4
    assert not any(d.accepted for d in decisions[1:]) and guard.n_non_finite == 4
    warnings = [r for r in caplog.records if "treating the match as a fault" in r.getMessage()]
    assert len(warnings) == 1 and "nan" in warnings[0].getMessage()


def test_guard_refuses_a_nan_threshold() -> None:
    class NaNThreshold(NaNDetector):
        threshold = float("nan")

    with pytest.raises(ConfigError, match=r"not a probability in \[0, 1\]"):
        ScanGuard(NaNThreshold(), get_matcher("icp"), GuardConfig(update_map=False))
    with pytest.raises(ValueError):
        GuardConfig(baseline_threshold=float("nan"))


# --- item 24 and recordings-only evaluation ---------------------------------------------------


@pytest.fixture(scope="module")
def recordings_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("rec")
    logs = [write_corrected_log(d / f"r{k}-corrected.log", seed=10 + k) for k in range(2)]
    build_from_recordings(logs, d / "store", CFG, progress=False)
    return d / "store"


def _detector(scores: Any) -> FaultDetector:
    det = FaultDetector(build_model(get_preset("tiny")), STYLE, 0.5, source="nan-model.pt")

    def predict(images: Any, *a: Any, **kw: Any) -> np.ndarray:
        return np.resize(np.asarray(scores, dtype=np.float64), len(images))

    det.predict_images = predict  # type: ignore[method-assign]
    return det


def test_evaluate_with_nan_model(recordings_store: Path) -> None:
    from scanguard.detect.evaluate import evaluate_store

    with pytest.raises(ModelError, match="not finite for any") as err:
        evaluate_store(_detector([np.nan]), recordings_store, baselines=[], splits=None)
    assert str(err.value).startswith("nan-model.pt") and "\n" not in str(err.value)
    res = evaluate_store(_detector([0.1, np.nan]), recordings_store, baselines=[], splits=None)
    assert res.meta["non_finite_scores"] == {"cnn": 5}
    row = res.row("cnn")
    assert row["TP"] + row["FP"] + row["n_ambiguous"] * row["ambiguous_flagged"] >= 4


def test_evaluate_recordings_only_says_how_to_fix(recordings_store: Path) -> None:
    from scanguard.detect.evaluate import evaluate_store

    with pytest.raises(ConfigError, match="--baseline-data") as err:
        evaluate_store(_detector([0.2]), recordings_store)
    assert "--baselines none" in str(err.value) and "\n" not in str(err.value)
