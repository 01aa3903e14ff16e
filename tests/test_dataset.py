import importlib.util
from pathlib import Path

import numpy as np
import pytest

from scanguard.dataset import (
    DatasetConfig,
    PairStore,
    build_dataset,
    label_sequence,
    merge_stores,
    plan_build,
    tasks,
    write_sequence_file,
)
from scanguard.dataset.planning import PlannedSequence
from scanguard.detect.images import render_all
from scanguard.detect.render import RenderStyle
from scanguard.errors import ConfigError, InputError
from scanguard.geometry import compose, relative
from scanguard.matching import get_matcher
from scanguard.matching.result import MatchResult
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL, LabelConfig, assign_labels, pair_errors
from scanguard.scan import SensorInfo
from tests.helpers import make_sequence, room_segments

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

SMALL = SensorInfo(
    name="small",
    n_beams=360,
    angle_min=-np.pi,
    angle_increment=2 * np.pi / 360,
    range_min=0.1,
    range_max=20.0,
    rate_hz=10.0,
)


def room_sequence(seed: int, n: int = 8, name: str = "room"):
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
        sensor=SMALL,
        noise=0.005,
        seed=seed,
        name=name,
    )


class InjectingMatcher:
    """Returns reference ⊕ a known error for each pair (ignores the scans)."""

    def __init__(self, reference_steps, errors):
        self.steps = list(reference_steps)
        self.errors = list(errors)
        self.k = 0

    def __call__(self, source, target, initial=None):
        pose = compose(self.steps[self.k], self.errors[self.k])
        self.k += 1
        return MatchResult(
            pose=pose,
            iterations=1,
            converged=True,
            reason="converged",
            mean_residual=0.0,
            median_residual=0.0,
            inlier_ratio=1.0,
            inlier_threshold=0.05,
        )


def test_injected_misalignment_gets_threshold_label():
    seq = room_sequence(1, n=5)
    ref = seq.reference
    steps = [relative(ref[k], ref[k + 1]) for k in range(4)]
    errors = [
        np.array([0.0, 0.0, 0.0]),
        np.array([0.25, 0.0, 0.0]),
        np.array([0.085, 0.0, 0.0]),
        np.array([0.0, 0.0, np.radians(3.0)]),
    ]
    rec = label_sequence(
        seq,
        environment="room",
        sequence="room_00",
        split="train",
        matcher=InjectingMatcher(steps, errors),
        matcher_name="inject",
        initial_guess="identity",
        labels=LabelConfig(),
        gmapping=False,
    )
    assert rec.pairs["label"].tolist() == [NORMAL, FAULT, AMBIGUOUS, FAULT]
    assert rec.pairs["disp_error"][1] == pytest.approx(0.25)
    assert rec.pairs["trans_error"][2] == pytest.approx(0.085)
    assert rec.pairs["rot_error"][3] == pytest.approx(np.radians(3.0))


def test_real_icp_on_static_room_is_normal():
    seq = room_sequence(2, n=6)
    rec = label_sequence(
        seq,
        environment="room",
        sequence="room_00",
        split="train",
        matcher=get_matcher("icp"),
        matcher_name="icp",
        initial_guess="identity",
        labels=LabelConfig(),
        gmapping=False,
    )
    assert (rec.pairs["label"] == NORMAL).all()
    assert rec.pairs["disp_error"].max() < LabelConfig().normal_displacement
    assert "inlier_ratio" in rec.metrics


def write_two(tmp_path):
    paths = []
    for k, split in enumerate(["train", "test"]):
        seq = room_sequence(10 + k, n=6)
        rec = label_sequence(
            seq,
            environment="room",
            sequence=f"room_{k:02d}",
            split=split,
            matcher=get_matcher("icp-paper"),
            matcher_name="icp-paper",
            initial_guess="identity",
            labels=LabelConfig(),
            gmapping=False,
        )
        paths.append(write_sequence_file(tmp_path / f"room_{k:02d}.h5", rec))
    return paths


def test_store_roundtrip_and_labels_reproducible(tmp_path):
    paths = write_two(tmp_path)
    store = PairStore.open(paths)
    r = store.records
    assert len(store) == 10
    assert set(r["sequence"].tolist()) == {"room_00", "room_01"}
    # every metric the store advertises is a column (iterations/converged were once dropped)
    for name in store.metric_names:
        assert r[name].shape == (10,), name
    assert {"iterations", "converged"} <= set(store.metric_names)
    assert (r["iterations"] >= 1).all()
    # labels are a pure function of the stored errors and the stored thresholds
    np.testing.assert_array_equal(store.relabel(store.label_config(0)), r["label"])
    # and the errors are reproducible from the stored scans, estimates and reference
    for i in range(len(store)):
        _, cur, est = store.pair_points(i)
        t, rot, d = pair_errors(est, r["reference"][i], cur.astype(np.float64))
        assert t == pytest.approx(r["trans_error"][i], abs=1e-9)
        assert rot == pytest.approx(r["rot_error"][i], abs=1e-9)
        assert d == pytest.approx(r["disp_error"][i], rel=1e-5, abs=1e-7)
    # other thresholds relabel without rebuilding
    strict = LabelConfig(
        fault_displacement=1e-6,
        normal_displacement=1e-6,
        fault_translation=1e-6,
        normal_translation=1e-6,
        fault_rotation_deg=1e-6,
        normal_rotation_deg=1e-6,
    )
    assert (store.relabel(strict) == FAULT).all()


def test_store_rejects_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="no such dataset"):
        PairStore.open(tmp_path / "missing.h5")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="HDF5"):
        PairStore.open(bad)
    paths = write_two(tmp_path)
    with pytest.raises(InputError, match="also in"):
        PairStore.open([paths[0], paths[0]])


def test_images_deterministic(tmp_path):
    from scanguard.detect.torch_data import PairDataset

    store = PairStore.open(write_two(tmp_path))
    style = RenderStyle.paper(size=64)
    a = render_all(store, np.arange(len(store)), style)
    b = render_all(PairStore.open(write_two(tmp_path / "again")), np.arange(len(store)), style)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (10, 64, 64, 3) and a.dtype == np.uint8
    ds = PairDataset(store, np.arange(len(store)), style)
    x, y = ds[3]
    assert x.shape == (3, 64, 64) and str(x.dtype) == "torch.float32"
    assert float(x.min()) >= 0.0 and float(x.max()) <= 1.0
    np.testing.assert_allclose(x.numpy(), a[3].transpose(2, 0, 1) / 255.0)
    assert int(y) == int(store.labels[3]) and str(y.dtype) == "torch.int64"
    # augmentation: same seed/epoch -> same image, other epoch -> other image
    aug1 = PairDataset(store, None, style, augment=True, seed=5)
    aug2 = PairDataset(store, None, style, augment=True, seed=5)
    np.testing.assert_array_equal(aug1[2][0].numpy(), aug2[2][0].numpy())
    aug2.set_epoch(1)
    assert not np.array_equal(aug1[2][0].numpy(), aug2[2][0].numpy())


def test_augmentation_keeps_alignment():
    from scanguard.detect.images import augment_pair
    from scanguard.geometry import inverse, transform_points

    rng = np.random.default_rng(0)
    prev = rng.uniform(-5, 5, (200, 2)).astype(np.float32)
    est = np.array([0.3, -0.1, 0.2])
    # current points expressed in the current frame so that est maps them onto prev
    cur = transform_points(inverse(est), prev).astype(np.float32)
    p2, c2, e2 = augment_pair(prev, cur, est, rng, rotation_deg=90, dropout=0.0)
    np.testing.assert_allclose(transform_points(e2, c2), p2, atol=1e-4)
    assert not np.allclose(p2, prev)


def fake_simulate(item: PlannedSequence):
    return room_sequence(item.seed, n=6, name=item.sequence)


def tiny_config(**kw) -> DatasetConfig:
    data = {
        "name": "tiny",
        "matcher": "icp-paper",
        "gmapping_score": False,
        "splits": {"val_sequences": 1, "test_sequences": 1, "seed": 3},
        "environments": [
            {"name": "lobby", "scenario": "lobby", "sequences": 4, "duration": 1.0, "seed": 0},
            {
                "name": "office",
                "scenario": "office",
                "sequences": 2,
                "duration": 1.0,
                "seed": 100,
                "heldout": True,
            },
        ],
    }
    data.update(kw)
    return DatasetConfig.from_dict(data)


def test_split_is_by_sequence():
    plan = plan_build(tiny_config())
    by_seq = {p.sequence: p.split for p in plan}
    assert len(by_seq) == len(plan) == 6
    lobby = [p.split for p in plan if p.environment.name == "lobby"]
    assert sorted(lobby) == ["test", "train", "train", "val"]
    assert all(p.split == "heldout" for p in plan if p.environment.name == "office")
    # deterministic
    assert [p.split for p in plan_build(tiny_config())] == [p.split for p in plan]


def test_build_resumes_to_identical_result(tmp_path, monkeypatch):
    monkeypatch.setattr(tasks, "_simulate", fake_simulate)
    cfg = tiny_config()
    full = build_dataset(cfg, tmp_path / "full", progress=False)
    assert len(full.built) == 6 and full.totals()["pairs"] == 30
    # interrupted after two sequences (plus a stray temp file from a killed write)
    part = build_dataset(cfg, tmp_path / "part", progress=False, max_sequences=2)
    assert len(part.built) == 2
    (tmp_path / "part" / "sequences" / ".lobby_02.h5.tmp123.h5").write_bytes(b"junk")
    resumed = build_dataset(cfg, tmp_path / "part", progress=False)
    assert sorted(resumed.skipped) == sorted(part.built) and len(resumed.built) == 4
    a, b = PairStore.open(tmp_path / "full"), PairStore.open(tmp_path / "part")
    assert a.records.keys() == b.records.keys()
    for key in a.records:
        np.testing.assert_array_equal(a.records[key], b.records[key], err_msg=key)
    for i in (0, 17, 29):
        for x, y in zip(a.pair_points(i), b.pair_points(i), strict=True):
            np.testing.assert_array_equal(x, y)
    ma = (tmp_path / "full" / "manifest.json").read_text()
    mb = (tmp_path / "part" / "manifest.json").read_text()
    assert ma == mb
    # the split keeps sequences on one side only
    r = a.records
    train = set(r["sequence"][a.indices("train", include_ambiguous=True)].tolist())
    test = set(r["sequence"][a.indices(["test", "val"], include_ambiguous=True)].tolist())
    held = set(r["sequence"][a.indices("heldout", include_ambiguous=True)].tolist())
    assert train and test and held
    assert not (train & test) and not (train & held) and not (test & held)
    assert held == {"office_00", "office_01"}
    # a changed config is refused instead of silently mixed
    with pytest.raises(ConfigError, match="another config"):
        build_dataset(
            tiny_config(labels={"fault_displacement": 0.2}), tmp_path / "part", progress=False
        )


def test_merge_and_open_list(tmp_path, monkeypatch):
    monkeypatch.setattr(tasks, "_simulate", fake_simulate)
    build_dataset(tiny_config(), tmp_path / "a", progress=False)
    paths = write_two(tmp_path / "b")
    both = PairStore.open([tmp_path / "a", *paths])
    assert len(both) == 40
    merged = PairStore.open(merge_stores([tmp_path / "a", *paths], tmp_path / "m"))
    np.testing.assert_array_equal(merged.records["label"], both.records["label"])
    assert merged.environments == ["lobby", "office", "room"]


def test_stats_and_export(tmp_path, monkeypatch):
    from scanguard.dataset import label_counts, write_stats
    from scanguard.detect.images import export_png

    monkeypatch.setattr(tasks, "_simulate", fake_simulate)
    build_dataset(tiny_config(), tmp_path / "a", progress=False)
    store = PairStore.open(tmp_path / "a")
    rows = label_counts(store)
    assert [r["environment"] for r in rows] == ["lobby", "office", "all"]
    assert rows[-1]["pairs"] == 30
    assert rows[-1]["normal"] + rows[-1]["fault"] + rows[-1]["ambiguous"] == 30
    _, js = write_stats(store, tmp_path / "stats")
    assert js.is_file() and (tmp_path / "stats" / "hist_lobby.png").stat().st_size > 1000
    written = export_png(store, tmp_path / "png", RenderStyle.paper(size=32), per_class=3)
    for env, counts in written.items():
        for cls, n in counts.items():
            assert len(list((tmp_path / "png" / env / cls).glob("*.png"))) == n


def test_labels_recomputed_match_store_after_build(tmp_path, monkeypatch):
    monkeypatch.setattr(tasks, "_simulate", fake_simulate)
    build_dataset(tiny_config(), tmp_path / "a", progress=False)
    store = PairStore.open(tmp_path / "a")
    r = store.records
    lab = assign_labels(r["trans_error"], r["rot_error"], r["disp_error"], LabelConfig())
    np.testing.assert_array_equal(lab, r["label"])


@pytest.mark.skipif(importlib.util.find_spec("scanguard.sim") is None, reason="no simulator")
def test_real_simulator_tiny_build(tmp_path):
    pytest.importorskip("scanguard.sim")
    from scanguard import sim

    if not hasattr(sim, "simulate"):
        pytest.skip("simulator not available yet")
    cfg = tiny_config(
        environments=[
            {"name": "lobby", "scenario": "lobby", "sequences": 1, "duration": 1.0, "seed": 0}
        ]
    )
    s = build_dataset(cfg, tmp_path / "sim", progress=False)
    store = PairStore.open(tmp_path / "sim")
    assert len(store) == s.totals()["pairs"] > 0
    np.testing.assert_array_equal(store.relabel(LabelConfig()), store.labels)


@pytest.mark.skipif(
    not (DATA / "carmen" / "intel-corrected.log.gz").exists(), reason="shared data absent"
)
def test_recording_build_from_carmen(tmp_path):
    io = pytest.importorskip("scanguard.io")
    if not hasattr(io, "read_sequence"):
        pytest.skip("readers not available yet")
    from scanguard.dataset import build_from_recording

    cfg = DatasetConfig(gmapping_score=False)
    s = build_from_recording(
        DATA / "carmen" / "intel-corrected.log.gz",
        tmp_path / "real",
        cfg,
        max_scans=12,
        progress=False,
    )
    store = PairStore.open(tmp_path / "real")
    assert len(store) == 11 and s.entries[0]["split"] == "heldout"
    # one labelling policy: the matcher starts where `run` starts it (identity), never from
    # odometry simulated from the reference
    assert store.file_attrs[0]["initial_guess"] == "identity"
    assert not store.records["initial"].any()
    # a corrected log has no odometry: the odometry input is masked for every pair
    assert np.isnan(store.records["odometry_increment"]).all()
    again = build_from_recording(
        DATA / "carmen" / "intel-corrected.log.gz",
        tmp_path / "real",
        cfg,
        max_scans=12,
        progress=False,
    )
    assert again.skipped == [s.built[0]]


def test_cli_build_stats_export(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from scanguard.cli import app

    monkeypatch.setattr(tasks, "_simulate", fake_simulate)
    cfg_path = tmp_path / "tiny.yaml"
    tiny_config().save(cfg_path)
    runner = CliRunner()
    res = runner.invoke(app, ["dataset", "build", "-c", str(cfg_path), "-o", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    store = PairStore.open(tmp_path / "d")
    assert len(store) == 30
    res = runner.invoke(app, ["dataset", "stats", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "d" / "stats" / "hist_office.png").is_file()
    total = [r for r in res.output.splitlines() if r.strip("│ ").startswith("all")]
    assert total and "30" in total[0]
    res = runner.invoke(
        app,
        [
            "dataset",
            "export-png",
            str(tmp_path / "d"),
            "-o",
            str(tmp_path / "png"),
            "-n",
            "2",
            "--size",
            "32",
        ],
    )
    assert res.exit_code == 0, res.output
    assert len(list((tmp_path / "png").glob("*/*/*.png"))) > 0
    # errors are one red line, exit 1
    res = runner.invoke(app, ["dataset", "stats", str(tmp_path / "nope")])
    assert res.exit_code == 1 and "no such dataset" in res.output


@pytest.mark.skipif(
    not (DATA / "carmen" / "intel-corrected.log.gz").exists(), reason="shared data absent"
)
def test_run_and_dataset_build_label_the_same_matches(tmp_path):
    """The same recording gets the same labels from the online guard and from a build."""
    from scanguard.dataset import build_from_recording
    from scanguard.io import read_sequence
    from scanguard.matching import get_matcher
    from scanguard.slam.guard import GuardConfig
    from scanguard.slam.oracle import reference_labels
    from scanguard.slam.stream import ScanGuard

    log_path = DATA / "carmen" / "intel-corrected.log.gz"
    seq = read_sequence(log_path).subsequence(slice(0, 16))
    build_from_recording(
        log_path,
        tmp_path / "real",
        DatasetConfig(gmapping_score=False),
        max_scans=16,
        progress=False,
    )
    built = PairStore.open(tmp_path / "real")

    class Never:
        threshold = 0.5

        def fault_probability(self, previous, current, pose) -> float:
            return 0.0

    guard = ScanGuard(Never(), get_matcher("icp-paper"), GuardConfig(policy="none"))
    est = []
    for k, scan in enumerate(seq.scans):
        d = guard.step(scan)
        if k:
            est.append(d.match.pose if d.match is not None else np.full(3, np.nan))
    run_labels = reference_labels(seq, np.array(est), built.label_config())
    np.testing.assert_array_equal(built.labels, run_labels)
    # the guard matches float32 points, the build float64 ones: equal to ~1e-7 m
    np.testing.assert_allclose(built.records["estimate"], np.array(est), atol=1e-6)
    # more than one label occurs, so the comparison means something on these 1 m steps
    assert len(set(built.labels.tolist())) >= 2
