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
) -> tuple[Any, dict[str, Any], Path]:
    """Fit a calibration of ``model`` on ``recording``'s self-supervised labels.

    Args:
        recording: The user's recording (no reference needed).
        model: A ``model.pt`` (None: the shipped model of the default matcher).
        method: ``temperature`` or ``platt``.
        max_scans: Only the first N scans (the first pass and the labels).
        scan_topic: LaserScan topic (None: the only one).
        odom_topic: Odometry topic.

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
        fit, report = calibrate_model(chosen, source, method=method)
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
