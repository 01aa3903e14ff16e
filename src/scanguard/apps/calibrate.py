"""The ``calibrate`` workflow: label pairs, fit a calibration, write the recalibrated model.

The pairs come from recordings with a reference (labelled by the model's own label rule, in
a temporary build that is removed afterwards) or from labelled pair stores. The outputs are
``model.pt`` (the original plus a calibration block), ``calibration.json``/``.md`` and two
reliability diagrams.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from scanguard.apps.report import ReportTable, fmt

logger = logging.getLogger(__name__)

#: Calibration methods of `calibrate_model`.
METHODS = ("temperature", "platt")
#: Threshold rules of `calibrate_model` (`scanguard.detect.calibrate.THRESHOLD_RULES`).
THRESHOLD_RULES = ("balanced_accuracy", "keep")

#: Files `write_calibration` writes, besides ``model.pt``.
REPORT_FILES = (
    "calibration.json",
    "calibration.md",
    "reliability_before.png",
    "reliability_after.png",
)


@dataclasses.dataclass(frozen=True)
class RecordingPairs:
    """Recordings whose consecutive pairs are labelled against a reference for calibration.

    Attributes:
        paths: The recordings.
        reference: A TUM file or ``static`` (None: the recordings' own reference).
        max_scans: Only the first N scans of each.
        scan_topic: LaserScan topic (None: the only one).
        odom_topic: Odometry topic.
        reference_topic: Reference pose topic.
        initial_guess: What seeds the matcher when the pairs are labelled (``auto``: the
            paper's identity; ``odometry``: the wheels, as the fused default seeds plicp).
        reference_name: How the report names the reference (None: its file name); the
            self-supervised labels of ``calibrate --self`` say what they are here.
    """

    paths: Sequence[str]
    reference: str | None = None
    max_scans: int | None = None
    scan_topic: str | None = None
    odom_topic: str | None = None
    reference_topic: str | None = None
    initial_guess: str = "auto"
    reference_name: str | None = None

    def __post_init__(self) -> None:
        # the input-path check of `run` and `info`, before the model loads: a FIFO or a
        # device would block the labelling (or never end) instead of failing
        from scanguard.io import check_recording_path
        from scanguard.safeload import check_input_file

        for path in self.paths:
            check_recording_path(path)
        if self.reference is not None and self.reference.lower() != "static":
            check_input_file(self.reference, what="TUM reference file")

    def describe(self) -> str:
        """What the calibration was fitted on, for the report."""
        where = ", ".join(Path(r).name for r in self.paths)
        if self.reference_name:
            return f"{where} ({self.reference_name})"
        if self.reference:
            ref = Path(self.reference).name if self.reference != "static" else self.reference
            where += f" (reference {ref})"
        return where


def _label_recordings(detector: Any, source: RecordingPairs, pairs_dir: str) -> None:
    """Label ``source``'s pairs into ``pairs_dir`` with the matcher and labels of ``detector``."""
    from scanguard.dataset import DatasetConfig
    from scanguard.dataset.build import build_from_recordings

    cfg_data: dict[str, Any] = {"matcher": getattr(detector, "matchers", ("icp-paper",))[0]}
    if detector.label_thresholds:  # the model's own label rule
        cfg_data["labels"] = detector.label_thresholds
    cfg_data["recording_initial_guess"] = source.initial_guess
    cfg = DatasetConfig.from_dict(cfg_data, source=str(detector.source))
    build_from_recordings(
        list(source.paths),
        pairs_dir,
        cfg,
        reference=source.reference,
        max_scans=source.max_scans,
        progress=False,
        scan_topic=source.scan_topic,
        odom_topic=source.odom_topic,
        reference_topic=source.reference_topic,
    )


def calibrate_model(
    model: str | None,
    source: RecordingPairs | Sequence[str],
    *,
    method: str = "temperature",
    splits: Sequence[str] | None = None,
    threshold_rule: str = "balanced_accuracy",
) -> tuple[Any, dict[str, Any]]:
    """Fit a calibration of ``model`` on the labelled pairs of ``source``.

    Args:
        model: A ``model.pt`` (None: the shipped model).
        source: Recordings with a reference, or pair store(s) (folders, ``.h5`` files).
        method: ``temperature`` or ``platt``.
        splits: Splits of the stores to use (None: every pair); unused for recordings.
        threshold_rule: ``balanced_accuracy`` (the project rule) or ``keep`` (the model's
            decision boundary, `scanguard.detect.recalibrate.calibrate_detector`).

    Returns:
        The `CalibrationFit` and the JSON report (model, calibration, metrics before/after).
    """
    from scanguard.detect.detector import FaultDetector
    from scanguard.detect.recalibrate import calibrate_detector

    det = FaultDetector.load(model)
    with contextlib.ExitStack() as stack:
        if isinstance(source, RecordingPairs):
            pairs_dir = stack.enter_context(tempfile.TemporaryDirectory(prefix="scanguard-cal-"))
            _label_recordings(det, source, pairs_dir)
            store: Any = pairs_dir
            where = source.describe()
            splits = None
        else:
            store = list(source) if len(source) > 1 else source[0]
            where = ", ".join(Path(d).name for d in source)
        fit = calibrate_detector(
            det, store, method=method, splits=splits, fitted_on=where,  # type: ignore[arg-type]
            threshold_rule=threshold_rule,  # type: ignore[arg-type]
        )  # fmt: skip
    logger.info("calibrated %s on %d pairs (%s)", det.source, fit.calibration.n_pairs, method)
    return fit, {"model": det.source, **fit.report()}


def write_calibration(
    model: str | None, fit: Any, report: dict[str, Any], dest: str | Path, method: str
) -> None:
    """Write the recalibrated model, the report and the reliability diagrams into ``dest``."""
    from scanguard.detect.calibrate import plot_reliability
    from scanguard.detect.recalibrate import save_calibrated
    from scanguard.fsutil import atomic_write_text

    dest = Path(dest)
    save_calibrated(model, fit.calibration, dest / "model.pt")
    atomic_write_text(dest / "calibration.json", json.dumps(report, indent=2) + "\n")
    atomic_write_text(dest / "calibration.md", calibration_markdown(report))
    plot_reliability(
        [("before", fit.labels, fit.proba_before)],
        dest / "reliability_before.png",
        title="before calibration",
    )
    plot_reliability(
        [("after", fit.labels, fit.proba_after)],
        dest / "reliability_after.png",
        title=f"after {method} calibration",
    )


_METRICS = ("threshold", "accuracy", "balanced_accuracy", "recall", "precision", "f1", "ece")


def calibration_markdown(report: dict[str, Any]) -> str:
    """The calibration report as Markdown (parameters, metrics before and after)."""
    cal = report["calibration"]
    params = (
        f"temperature T = {cal['temperature']:.4f} (p = sigmoid(z / T))"
        if cal["method"] == "temperature"
        else f"Platt a = {cal['a']:.4f}, b = {cal['b']:.4f} (p = sigmoid(a z + b))"
    )
    pairs = report["pairs"]
    lines = [
        "# Calibration",
        "",
        f"* model: `{report['model']}`",
        f"* fitted on: {cal['fitted_on']}",
        f"* pairs: {pairs['normal']} normal, {pairs['fault']} fault, "
        f"{pairs['ambiguous']} ambiguous (excluded)",
        f"* method: {cal['method']}; {params}",
        f"* threshold rule: {_rule_text(cal)}: **{cal['threshold']:.4f}**",
        "",
        "| | threshold | accuracy | balanced accuracy | recall | precision | F1 | ECE |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key in ("before", "after"):
        m = report[key]
        lines.append(f"| {key} | " + " | ".join(fmt(m[k]) for k in _METRICS) + " |")
    lines += [
        "",
        "Reliability diagrams: `reliability_before.png`, `reliability_after.png` (15 "
        "equal-width bins of the fault probability).",
        "",
    ]
    return "\n".join(lines)


def _rule_text(cal: dict[str, Any]) -> str:
    if (cal.get("extra") or {}).get("threshold_rule") == "keep":
        return "keep the model's decision boundary (the same fault logit; no verdict changes)"
    return "maximise balanced accuracy, ties -> closest to 0.5"


def calibration_table(report: dict[str, Any], method: str, n_pairs: int) -> ReportTable:
    """Threshold and metrics before and after the calibration."""
    t = ReportTable(
        f"calibration ({method}) on {n_pairs} labelled pairs",
        [("", False), *((k, True) for k in ("threshold", "accuracy", "bal. acc.", "F1", "ECE"))],
    )
    for key in ("before", "after"):
        m = report[key]
        t.add_row(
            key,
            fmt(m["threshold"]),
            fmt(m["accuracy"], pct=True),
            fmt(m["balanced_accuracy"]),
            fmt(m["f1"], pct=True),
            fmt(m["ece"]),
        )
    return t
