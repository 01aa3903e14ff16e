"""``scanguard calibrate``: recalibrate a model (temperature or Platt) on labelled pairs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from scanguard.apps.calibrate import (
    METHODS,
    REPORT_FILES,
    THRESHOLD_RULES,
    RecordingPairs,
    calibrate_model,
    calibration_table,
    write_calibration,
)
from scanguard.cli.checks import Bound, checked, result_dir
from scanguard.cli.main import app, console, guarded
from scanguard.cli.options import (
    Data,
    MaxScans,
    Model,
    OdomTopic,
    Out,
    Overwrite,
    Recordings,
    Reference,
    ReferenceTopic,
    ScanTopic,
    Split,
)
from scanguard.cli.render import rich_table
from scanguard.errors import ConfigError


@app.command()
@guarded
@checked(max_scans=Bound(low=2))
def calibrate(
    ctx: typer.Context,
    out: Out,
    model: Model = None,
    recording: Recordings = [],  # noqa: B006 - typer never mutates it
    reference: Reference = None,
    data: Data = [],  # noqa: B006
    split: Split = ["all"],  # noqa: B006
    method: Annotated[
        str, typer.Option("--method", metavar="NAME", help="temperature or platt.")
    ] = "temperature",
    max_scans: MaxScans = None,
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    reference_topic: ReferenceTopic = None,
    overwrite: Overwrite = False,
    self_recording: Annotated[
        str | None,
        typer.Option(
            "--self",
            metavar="RECORDING",
            help="Calibrate on this recording with no reference: self-supervised labels from "
            "a first pass of the default SLAM (every scan processed), named as such.",
        ),
    ] = None,
    threshold_rule: Annotated[
        str | None,
        typer.Option(
            "--threshold-rule",
            metavar="RULE",
            help="balanced_accuracy (maximise it on the labelled pairs) or keep (the model's "
            "decision boundary: only the probabilities change). Default: balanced_accuracy; "
            "keep with --self, where the other measured worse (README).",
        ),
    ] = None,
) -> None:
    """Recalibrate a model (temperature or Platt, and its threshold) on labelled pairs.

    The pairs of --recording are labelled with its reference by the model's own label rule;
    or give labelled pair stores with --data. The recalibrated model (the original plus a
    calibration block) is written to OUT/model.pt, with calibration.json/.md and PNGs.
    """
    if method not in METHODS:
        raise ConfigError(f"--method must be temperature or platt, got {method!r}")
    if threshold_rule is not None and threshold_rule not in THRESHOLD_RULES:
        raise ConfigError(
            f"--threshold-rule must be {' or '.join(THRESHOLD_RULES)}, got {threshold_rule!r}"
        )
    if self_recording is not None:
        if recording or data or reference or reference_topic:
            raise ConfigError("--self takes no --recording, --data or reference: it has none")
        _calibrate_self(ctx, out, self_recording, model, method, max_scans, scan_topic,
                        odom_topic, overwrite, threshold_rule or "keep")  # fmt: skip
        return
    if bool(recording) == bool(data):
        raise ConfigError("give --recording PATH (with a reference) or --data STORE, not both")
    topics = (scan_topic, odom_topic, reference_topic)
    if (any(t is not None for t in topics) or reference or max_scans) and not recording:
        raise ConfigError("--reference/--max-scans/--*-topic apply to --recording only")
    result = result_dir(ctx, out, overwrite)  # before any long work
    source = (
        RecordingPairs(
            recording,
            reference=reference,
            max_scans=max_scans,
            scan_topic=scan_topic,
            odom_topic=odom_topic,
            reference_topic=reference_topic,
        )
        if recording
        else data
    )
    splits = None if "all" in split else list(split)
    rule = threshold_rule or "balanced_accuracy"
    fit, report = calibrate_model(model, source, method=method, splits=splits, threshold_rule=rule)
    with result as tmp:
        write_calibration(model, fit, report, tmp, method)
    _print_result(fit, report, method, out)


def _calibrate_self(
    ctx: typer.Context, out: str, rec: str, model: str | None, method: str,
    max_scans: int | None, scan_topic: str | None, odom_topic: str | None, overwrite: bool,
    threshold_rule: str,
) -> None:  # fmt: skip
    """``calibrate --self``: a first pass, self-supervised labels, the refitted calibration."""
    from scanguard.apps.self_calibrate import keep_first_pass, self_calibrate_model
    from scanguard.io import check_recording_path

    check_recording_path(rec)
    result = result_dir(ctx, out, overwrite)  # before any long work
    with console.status("first pass (every scan processed), then the self-supervised labels"):
        fit, report, work = self_calibrate_model(
            rec, model=model, method=method, max_scans=max_scans, scan_topic=scan_topic,
            odom_topic=odom_topic, threshold_rule=threshold_rule,
        )  # fmt: skip
    with result as tmp:
        kept = keep_first_pass(work, Path(tmp))
        write_calibration(report["model"], fit, report, tmp, method)
    console.print(f"labels: {report['labels']} ({', '.join(p.name for p in kept)})")
    _print_result(fit, report, method, out)


def _print_result(fit: Any, report: dict[str, Any], method: str, out: str) -> None:
    """The calibration table and where the model went."""
    from rich.markup import escape

    console.print(rich_table(calibration_table(report, method, fit.calibration.n_pairs)))
    cal = fit.calibration.to_dict()
    params = ", ".join(f"{k} {cal[k]:.4f}" for k in ("temperature", "a", "b") if k in cal)
    console.print(
        f"{params}; recalibrated model in [bold]{escape(str(Path(out) / 'model.pt'))}[/bold] "
        f"({', '.join(REPORT_FILES)})"
    )
