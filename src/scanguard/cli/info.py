"""``scanguard info``: summarise a recording."""

from __future__ import annotations

from typing import Annotated, Any

import typer

from scanguard.cli.main import app, console, guarded, printable
from scanguard.cli.options import (
    Corrected,
    Lenient,
    OdomTopic,
    Reference,
    ReferenceTopic,
    ScanTopic,
)


@app.command()
@guarded
def info(
    path: Annotated[
        str, typer.Argument(help="Bag (.bag, .mcap, .db3, ROS 2 folder) or CARMEN log.")
    ],
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    reference_topic: ReferenceTopic = None,
    reference: Reference = None,
    format: Annotated[
        str | None,
        typer.Option(
            "--format",
            metavar="NAME",
            help="Reader (rosbag, carmen) when the extension does not say.",
        ),
    ] = None,
    lenient: Lenient = False,
    corrected: Corrected = None,
) -> None:
    """Summarise a recording: scans, beams, field of view, rate, odometry, reference, topics."""
    from scanguard.io import read_sequence, summarize

    seq = read_sequence(
        path,
        format=format,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
        reference=reference,
        reader_options=None if corrected is None else {"corrected": corrected},
        lenient=lenient,
    )
    console.print(_summary_table(path, summarize(seq)))


def _summary_table(path: str, s: dict[str, Any]) -> Any:
    """The rich table of `scanguard.io.summarize`'s summary (file content escaped)."""
    from rich.markup import escape
    from rich.table import Table

    unknown = "unknown (see note)" if s["stamps_note"] else "unknown"
    table = Table(title=escape(printable(path)), show_header=False, title_justify="left")
    table.add_column("what", style="bold", no_wrap=True)
    table.add_column("value", overflow="fold")
    table.add_row("format", f"{s['format']} (sensor: {s['sensor']})")
    table.add_row("scans", str(s["scans"]))
    table.add_row("beams", " / ".join(str(b) for b in s["beams"]))
    table.add_row("field of view", f"{s['fov_deg']:.1f} deg")
    table.add_row("range limits", f"{s['range_min']:.2f} .. {s['range_max']:.2f} m")
    table.add_row("rate", unknown if s["rate_hz"] is None else f"{s['rate_hz']:.2f} Hz")
    table.add_row("duration", unknown if s["duration_s"] is None else f"{s['duration_s']:.1f} s")
    table.add_row("invalid beams", f"{100 * s['invalid_fraction']:.1f} %")
    odo = f"yes ({s['odometry_source']})" if s["odometry"] else "no"
    if s.get("odometry_note"):
        odo = f"{odo}; {s['odometry_note']}"
    table.add_row("odometry", escape(printable(odo)))
    ref = f"yes ({s['reference_kind']}: {s['reference_source']})" if s["reference"] else "no"
    table.add_row("reference", ref)
    off = s["laser_offset"]
    table.add_row("laser offset", f"x {off[0]:.3f} m, y {off[1]:.3f} m, yaw {off[2]:.3f} rad")
    topics = "\n".join(
        f"{escape(printable(name))}  [dim]{escape(printable(str(t['type'])))}[/dim]  {t['count']}"
        for name, t in sorted(s["topics"].items())
    )
    table.add_row("topics found", topics or "-")
    if s.get("other_lines"):
        other = ", ".join(f"{k} ({v})" for k, v in s["other_lines"].items())
        table.add_row("other lines", escape(printable(other)))
    if s.get("stamps_steps_back"):
        table.add_row("stamps", f"{s['stamps_steps_back']} steps back in file order (kept)")
    if s.get("skipped"):
        table.add_row("skipped (--lenient)", str(s["skipped"]))
    if s["stamps_note"]:
        table.add_row("note", f"[yellow]{escape(printable(s['stamps_note']))}[/yellow]")
    return table
