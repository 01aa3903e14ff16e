"""Command-line interface: parses arguments, calls the library, prints results.

Heavy modules (torch, rosbags, matplotlib) are imported inside the commands so that
``scanguard --help`` stays fast.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import typer
from rich.console import Console

from scanguard import __version__
from scanguard.errors import ScanGuardError

app = typer.Typer(
    name="scanguard",
    help="Detect faulty 2D LiDAR scan matches with a CNN and keep SLAM honest.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)

F = TypeVar("F", bound=Callable[..., Any])


def guarded(fn: F) -> F:
    """Turn expected errors (`ScanGuardError`) into one red line on stderr and exit code 1."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ScanGuardError as exc:
            err_console.print(f"[bold red]error:[/bold red] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None

    return wrapper  # type: ignore[return-value]


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"scanguard {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version."
    ),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
) -> None:
    """Detect faulty 2D LiDAR scan matches (global options)."""
    from scanguard.logging_utils import configure_logging

    configure_logging(verbose)


# --- commands: info (io) ---------------------------------------------------------------------


@app.command()
@guarded
def info(
    path: str = typer.Argument(..., help="Bag (.bag, .mcap, .db3, ROS 2 folder) or CARMEN log."),
    scan_topic: str | None = typer.Option(
        None, "--scan-topic", help="LaserScan topic (CARMEN: FLASER, RLASER, ROBOTLASER1)."
    ),
    odom_topic: str | None = typer.Option(
        None, "--odom-topic", help="Odometry topic (CARMEN: ODOM or laser)."
    ),
    reference_topic: str | None = typer.Option(
        None, "--reference-topic", help="Reference pose topic (Odometry or PoseStamped)."
    ),
    reference: str | None = typer.Option(
        None, "--reference", help="TUM trajectory file, or 'static' (sensor never moved)."
    ),
    format: str | None = typer.Option(
        None, "--format", help="Reader (rosbag, carmen) when the extension does not say."
    ),
) -> None:
    """Summarise a recording: scans, beams, field of view, rate, odometry, reference, topics."""
    from rich.table import Table

    from scanguard.io import read_sequence, summarize

    seq = read_sequence(
        path,
        format=format,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
        reference=reference,
    )
    s = summarize(seq)
    unknown = "unknown (see note)" if s["stamps_note"] else "unknown"
    table = Table(title=f"{path}", show_header=False, title_justify="left")
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("format", f"{s['format']} (sensor: {s['sensor']})")
    table.add_row("scans", str(s["scans"]))
    table.add_row("beams", " / ".join(str(b) for b in s["beams"]))
    table.add_row("field of view", f"{s['fov_deg']:.1f} deg")
    table.add_row("range limits", f"{s['range_min']:.2f} .. {s['range_max']:.2f} m")
    table.add_row("rate", unknown if s["rate_hz"] is None else f"{s['rate_hz']:.2f} Hz")
    table.add_row("duration", unknown if s["duration_s"] is None else f"{s['duration_s']:.1f} s")
    table.add_row("invalid beams", f"{100 * s['invalid_fraction']:.1f} %")
    table.add_row("odometry", f"yes ({s['odometry_source']})" if s["odometry"] else "no")
    ref = f"yes ({s['reference_kind']}: {s['reference_source']})" if s["reference"] else "no"
    table.add_row("reference", ref)
    off = s["laser_offset"]
    table.add_row("laser offset", f"x {off[0]:.3f} m, y {off[1]:.3f} m, yaw {off[2]:.3f} rad")
    topics = "\n".join(
        f"{name}  [dim]{t['type']}[/dim]  {t['count']}" for name, t in sorted(s["topics"].items())
    )
    table.add_row("topics found", topics or "-")
    if s["stamps_note"]:
        table.add_row("note", f"[yellow]{s['stamps_note']}[/yellow]")
    console.print(table)

# --- commands: simulate (sim) ----------------------------------------------------------------

# --- commands: dataset (dataset) -------------------------------------------------------------

# --- commands: train / evaluate / export (model) ---------------------------------------------

# --- commands: run / demo (pipeline) ---------------------------------------------------------
