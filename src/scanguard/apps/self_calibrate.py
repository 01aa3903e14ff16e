"""``calibrate --self``: recalibrate the judge on the user's own recording, with no reference.

Self-supervised labels, named as such everywhere: a **first pass** runs the default SLAM on the
recording with every scan processed by GMapping (``temporalUpdate: 0``), so that each pose of
its trajectory is a scan-to-map estimate of that scan, not one interpolated by the motion
between filter updates (which would be built from the very matches it is to judge). Each
consecutive scan-to-scan match is then labelled against that trajectory by the model's own
label rule, exactly as `scanguard calibrate` labels against a reference, and the calibration
(temperature or Platt, and the threshold by the project rule) is refitted on those labels.
The first pass's trajectory and summary are kept next to the model, so that what the labels
came from can be inspected.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scanguard.apps.calibrate import RecordingPairs, calibrate_model

logger = logging.getLogger(__name__)

#: Files of the first pass kept in the output folder (prefixed ``first_pass_``).
FIRST_PASS_FILES = ("trajectory.tum", "summary.md", "map.png")

#: How the report names the labels.
SELF_SUPERVISED = (
    "self-supervised labels: the first pass's own GMapping trajectory, every scan processed; "
    "not a reference"
)


def first_pass(
    recording: str,
    work: Path,
    *,
    model: str | None,
    max_scans: int | None,
    scan_topic: str | None,
    odom_topic: str | None,
) -> tuple[Path, bool]:
    """Run the default guarded SLAM densely on ``recording`` into ``work``.

    Returns:
        The trajectory file, and whether the recording has odometry.
    """
    from scanguard.apps.run import run_recording
    from scanguard.detect.detector import FaultDetector
    from scanguard.io import read_sequence
    from scanguard.slam.config import RunConfig

    # GMapping with every scan processed gives a pose per scan from the filter itself; the
    # default graph would give nodes 0.1 m apart with odometry in between
    cfg = RunConfig(backend="gmapping", compare=False, max_scans=max_scans)
    cfg.gmapping = cfg.gmapping.model_copy(update={"temporalUpdate": 0.0})
    seq = read_sequence(
        recording, scan_topic=scan_topic, odom_topic=odom_topic, max_scans=max_scans
    )
    detector = FaultDetector.load(model, backend="onnx", matcher=cfg.matcher)
    logger.info("first pass over %s (%d scans, every scan processed)", recording, len(seq))
    run_recording(seq, detector, work, config=cfg)
    return work / "trajectory.tum", seq.odometry is not None


def self_calibrate_model(
    recording: str,
    *,
    model: str | None = None,
    method: str = "temperature",
    max_scans: int | None = None,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    threshold_rule: str = "keep",
) -> tuple[Any, dict[str, Any], Path]:
    """Fit a calibration of ``model`` on ``recording``'s self-supervised labels.

    Args:
        recording: The user's recording (no reference needed).
        model: A ``model.pt`` (None: the shipped model of the default matcher).
        method: ``temperature`` or ``platt``.
        max_scans: Only the first N scans (the first pass and the labels).
        scan_topic: LaserScan topic (None: the only one).
        odom_topic: Odometry topic.
        threshold_rule: ``keep`` (the model's decision boundary; the default: maximising
            balanced accuracy on the self-supervised labels cut specificity on verified
            relation pairs to 0.11-0.73, README) or ``balanced_accuracy``.

    Returns:
        The `CalibrationFit`, its JSON report, and a temporary folder holding the first pass
        (the caller copies what it keeps and removes it).
    """
    from scanguard.detect.detector import default_model_path
    from scanguard.slam.config import RunConfig

    chosen = model if model is not None else str(default_model_path(RunConfig().matcher))
    work = Path(tempfile.mkdtemp(prefix="scanguard-self-"))
    try:
        trajectory, wheels = first_pass(
            recording,
            work / "first_pass",
            model=chosen,
            max_scans=max_scans,
            scan_topic=scan_topic,
            odom_topic=odom_topic,
        )
        source = RecordingPairs(
            [recording],
            reference=str(trajectory),
            max_scans=max_scans,
            scan_topic=scan_topic,
            odom_topic=odom_topic,
            # the fused default seeds its matcher with the wheels: label those matches
            initial_guess="odometry" if wheels else "auto",
            reference_name=SELF_SUPERVISED,
        )
        fit, report = calibrate_model(chosen, source, method=method, threshold_rule=threshold_rule)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    report["labels"] = SELF_SUPERVISED
    return fit, report, work


def keep_first_pass(work: Path, out: Path) -> list[Path]:
    """Copy the first pass's `FIRST_PASS_FILES` into ``out`` (prefixed) and remove ``work``."""
    from scanguard.fsutil import atomic_write_bytes

    kept = []
    try:
        for name in FIRST_PASS_FILES:
            src = work / "first_pass" / name
            if src.is_file():
                dst = out / f"first_pass_{name}"
                atomic_write_bytes(dst, src.read_bytes())
                kept.append(dst)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return kept


def self_calibrated_detector(
    recording: str,
    dest: Path,
    *,
    model: str | None,
    matcher: str,
    runtime: str = "onnx",
    method: str = "temperature",
    max_scans: int | None = None,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
) -> tuple[Any, dict[str, Any]]:
    """``run --self-calibrate``: self-calibrate the run's model, keep it in ``dest``, load it.

    The same first pass and self-supervised labels as ``calibrate --self``; ``dest`` receives
    what that command writes (``model.pt``, ``calibration.json/.md``, the reliability
    diagrams, ``first_pass_*``).

    Args:
        recording: The recording the run is about to process.
        dest: Folder for the recalibrated model and its report (created).
        model: The run's model (None: the shipped model of ``matcher``).
        matcher: The run's matcher (its shipped model, and the loaded detector's check).
        runtime: CNN runtime of the loaded detector (``onnx`` or ``torch``).
        method: ``temperature`` or ``platt``.
        max_scans: Only the first N scans.
        scan_topic: LaserScan topic.
        odom_topic: Odometry topic.

    Returns:
        The recalibrated detector and what changed (`self_calibration_summary`).
    """
    from scanguard.apps.calibrate import write_calibration
    from scanguard.detect.detector import FaultDetector, default_model_path

    chosen = model if model is not None else str(default_model_path(matcher))
    fit, report, work = self_calibrate_model(
        recording,
        model=chosen,
        method=method,
        max_scans=max_scans,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
    )
    dest.mkdir(parents=True, exist_ok=True)
    keep_first_pass(work, dest)
    write_calibration(report["model"], fit, report, dest, method)
    detector = FaultDetector.load(dest / "model.pt", backend=runtime, matcher=matcher)  # type: ignore[arg-type]
    return detector, self_calibration_summary(fit, report, method)


def self_calibration_summary(fit: Any, report: dict[str, Any], method: str) -> dict[str, Any]:
    """What a self-calibration changed: thresholds, parameters, pairs, agreement."""
    cal = fit.calibration.to_dict()
    pairs = report["pairs"]
    before = report["before"]
    return {
        "labels": SELF_SUPERVISED,
        "method": method,
        "pairs_normal": int(pairs["normal"]),
        "pairs_fault": int(pairs["fault"]),
        "pairs_ambiguous": int(pairs["ambiguous"]),
        "threshold_before": float(fit.threshold_before),
        "threshold_after": float(fit.calibration.threshold),
        **{k: float(cal[k]) for k in ("temperature", "a", "b") if k in cal},
        # the zero-shot model's accuracy on the self-supervised labels: how far it agreed
        "agreement_zero_shot": before.get("accuracy"),
        "balanced_accuracy_after": report["after"].get("balanced_accuracy"),
    }


@dataclass(frozen=True)
class SelfCalibration:
    """``run --self-calibrate``: the recording to recalibrate on, and how to read it."""

    recording: str
    scan_topic: str | None = None
    odom_topic: str | None = None

    def detector(
        self, dest: Path, model: str | None, cfg: Any, runtime: str = "onnx"
    ) -> tuple[Any, dict[str, Any]]:
        """`self_calibrated_detector` for a run of config ``cfg`` (its matcher, max_scans)."""
        return self_calibrated_detector(
            self.recording,
            dest,
            model=model,
            matcher=cfg.matcher,
            runtime=runtime,
            max_scans=cfg.max_scans,
            scan_topic=self.scan_topic,
            odom_topic=self.odom_topic,
        )
