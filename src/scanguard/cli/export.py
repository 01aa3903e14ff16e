"""``scanguard export onnx``: the fault-detection CNN as ONNX."""

from __future__ import annotations

from typing import Annotated

import typer

from scanguard.cli.main import app, console, guarded
from scanguard.cli.options import Model, OverwriteFile
from scanguard.cli.usage import UnixTyper

export_app = UnixTyper(help="Export the fault-detection model.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@export_app.command("onnx")
@guarded
def export_onnx_cmd(
    out: Annotated[
        str, typer.Option("--out", "-o", metavar="PATH", help="Destination .onnx file.")
    ],
    model: Model = None,
    overwrite: OverwriteFile = False,
) -> None:
    """Write the CNN as ONNX (inputs 'images' N x C x H x W in [0, 1] [+ 'metrics']; logits)."""
    from rich.markup import escape

    from scanguard.detect.detector import FaultDetector
    from scanguard.fsutil import check_output_path

    # before loading the model; an existing file (or a link) only with --overwrite
    check_output_path(
        out, "file", suffixes=(".onnx",), refuse_existing=None if overwrite else "--overwrite"
    )
    det = FaultDetector.load(model)
    path = det.export_onnx(out)
    h, w, c = det.input_shape
    metrics = ""
    if det.metric_names:
        metrics = (
            f" + metrics N x {len(det.metric_names)} (scanguard.detect.model.metric_inputs of "
            f"{', '.join(det.metric_names)})"
        )
    console.print(
        f"wrote [bold]{escape(str(path))}[/bold]: input images N x {c} x {h} x {w}{metrics}, "
        "output logits "
        f"N x 2 (fault = index 1, softmax then threshold {det.threshold:.3f}); "
        f"render style {det.style.kind} {det.style.size}px"
    )
