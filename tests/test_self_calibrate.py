"""``calibrate --self``: self-supervised labels from a first pass, named as such; no reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scanguard.apps.self_calibrate import FIRST_PASS_FILES, keep_first_pass
from scanguard.cli import app

runner = CliRunner()
EXCERPT = Path(__file__).parent / "data" / "ccny-excerpt.bag"


def test_self_takes_no_reference_and_no_other_source(tmp_path: Path) -> None:
    for extra in (["--recording", str(EXCERPT)], ["--reference", "static"], ["--data", "x"]):
        res = runner.invoke(app, ["calibrate", "--self", str(EXCERPT), "-o", str(tmp_path / "o"),
                                  *extra])  # fmt: skip
        assert res.exit_code == 1
        assert "--self takes no --recording, --data or reference" in res.output
        assert not (tmp_path / "o").exists()


def test_first_pass_files_are_kept_with_a_prefix_and_the_work_folder_goes(tmp_path: Path) -> None:
    work = tmp_path / "work"
    (work / "first_pass").mkdir(parents=True)
    for name in FIRST_PASS_FILES[:2]:  # a pass that wrote no map picture: skipped, no error
        (work / "first_pass" / name).write_text(name)
    out = tmp_path / "out"
    out.mkdir()
    kept = keep_first_pass(work, out)
    assert [p.name for p in kept] == [f"first_pass_{n}" for n in FIRST_PASS_FILES[:2]]
    assert (out / "first_pass_trajectory.tum").read_text() == "trajectory.tum"
    assert not work.exists()


@pytest.mark.slow
def test_a_recording_without_faults_is_refused_in_one_line_and_writes_nothing(
    tmp_path: Path,
) -> None:
    """The hand-carried excerpt: the first pass finds every match normal (0 self-supervised
    faults), and a calibration needs both classes: one line naming the labels, no output."""
    np.random.seed(0)
    out = tmp_path / "cal"
    res = runner.invoke(app, ["calibrate", "--self", str(EXCERPT), "-o", str(out)])
    assert res.exit_code == 1, res.output
    text = " ".join(res.output.split())
    assert "self-supervised labels: the first pass's own GMapping trajectory" in text
    assert "0 fault pair(s): a calibration needs at least 3 of each class" in text
    assert "Traceback" not in res.output
    assert not out.exists()


def test_the_first_pass_is_gmapping_with_a_pose_per_scan(tmp_path: Path, monkeypatch) -> None:
    """The labels need a pose of the filter's own at every scan, not one per graph node."""
    import scanguard.apps.run as run_module
    from scanguard.apps.self_calibrate import first_pass

    seen = {}

    def fake_run(seq, detector, out, *, config):  # type: ignore[no-untyped-def]
        seen["cfg"] = config
        seen["n"] = len(seq)

    monkeypatch.setattr(run_module, "run_recording", fake_run)
    bag = (
        Path(__file__).parents[2]
        / "shared"
        / "data"
        / "rosbag"
        / "ccny_laser_scan_matcher_demo.bag"
    )
    if not bag.exists():
        pytest.skip("the shared CCNY bag is not there")
    traj, has_odometry = first_pass(
        str(bag), tmp_path, model=None, max_scans=20, scan_topic=None, odom_topic=None
    )
    cfg = seen["cfg"]
    assert (cfg.backend, cfg.gmapping.temporalUpdate, cfg.compare) == ("gmapping", 0.0, False)
    assert seen["n"] == 20 and traj == tmp_path / "trajectory.tum" and not has_odometry


def test_run_self_calibrate_runs_with_the_recalibrated_model(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``run --self-calibrate``: the recalibrated model is written into the result folder,
    the run loads it, and the summary and metrics say what changed. The first pass and the
    labels are stood in for by a fit on known, seeded logits (they have their own tests)."""
    import json

    import scanguard.apps.self_calibrate as sc
    from scanguard.detect.calibrate import fit_calibration
    from scanguard.detect.detector import FaultDetector, default_model_path

    rng = np.random.default_rng(3)
    labels = np.r_[np.zeros(60, dtype=np.int64), np.ones(12, dtype=np.int64)]
    logits = np.r_[rng.normal(-3.0, 1.0, 60), rng.normal(2.0, 1.0, 12)]
    seen = {}

    def fake_model(recording, **kwargs):  # type: ignore[no-untyped-def]
        seen.update(kwargs, recording=recording)
        fit = fit_calibration(labels, logits, threshold_before=0.256, fitted_on="test")
        work = tmp_path / "work"
        (work / "first_pass").mkdir(parents=True)
        (work / "first_pass" / "trajectory.tum").write_text("# first pass\n")
        return fit, {"model": kwargs["model"], **fit.report()}, work

    monkeypatch.setattr(sc, "self_calibrate_model", fake_model)
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(EXCERPT), "-o", str(out), "--no-compare",
                              "--self-calibrate"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert seen["recording"] == str(EXCERPT)
    assert seen["model"] == str(default_model_path("plicp"))
    cal = out / "self_calibration"
    assert (cal / "model.pt").is_file() and (cal / "calibration.json").is_file()
    assert (cal / "first_pass_trajectory.tum").read_text() == "# first pass\n"
    assert not (tmp_path / "work").exists()
    want = fit_calibration(labels, logits, threshold_before=0.256).calibration
    assert FaultDetector.load(cal / "model.pt").threshold == pytest.approx(want.threshold)
    metrics = json.loads((out / "metrics.json").read_text())["self_calibration"]
    assert metrics["threshold_after"] == pytest.approx(want.threshold)
    assert (metrics["pairs_normal"], metrics["pairs_fault"]) == (60, 12)
    assert metrics["temperature"] == pytest.approx(want.to_dict()["temperature"])
    summary = " ".join((out / "summary.md").read_text().split())
    assert f"CNN threshold 0.256 -> {want.threshold:.3g}" in summary
    assert "self-supervised labels" in summary
    assert f"CNN threshold {want.threshold:.3g}" in summary  # the gate used the new model


def test_self_calibration_keeps_the_decision_boundary_by_default(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Maximising balanced accuracy on the few, noisy self-supervised faults cut specificity
    on verified relation pairs to 0.11-0.73 (README): ``--self`` keeps the model's boundary
    unless told otherwise, and says so in its report."""
    import scanguard.apps.self_calibrate as sc

    seen: list[str] = []

    def fake_pass(recording, work, **kwargs):  # type: ignore[no-untyped-def]
        work.mkdir(parents=True)
        (work / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")
        return work / "trajectory.tum", True

    def fake_calibrate(model, source, *, method, threshold_rule):  # type: ignore[no-untyped-def]
        seen.append(threshold_rule)
        return object(), {"model": model}

    monkeypatch.setattr(sc, "first_pass", fake_pass)
    monkeypatch.setattr(sc, "calibrate_model", fake_calibrate)
    for kwargs, want in (
        ({}, "keep"),
        ({"threshold_rule": "balanced_accuracy"}, "balanced_accuracy"),
    ):
        _, report, work = sc.self_calibrate_model(str(EXCERPT), **kwargs)
        assert report["labels"] == sc.SELF_SUPERVISED and seen[-1] == want
        keep_first_pass(work, tmp_path)
    assert seen == ["keep", "balanced_accuracy"]
    res = runner.invoke(app, ["calibrate", "--help"])
    assert "keep with --self" in " ".join(res.output.split())
