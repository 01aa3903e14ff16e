"""``scanguard run --realtime``: the recording at its sensor's rate, as the live node sees it."""

from __future__ import annotations

from typing import Annotated, Any

import typer

from scanguard.cli.main import console, err_console

Realtime = Annotated[
    bool,
    typer.Option(
        "--realtime",
        help="Play the recording at its sensor's rate into the live node (no ROS needed): "
        "the main (guarded) instance alone, a scan that arrives while the previous one is "
        "being processed is dropped, as on a robot. Reports per-scan latency (median, p99, "
        "max) and dropped scans in the summary and metrics.json. Takes as long as the "
        "recording.",
    ),
]

#: Options that do not go with ``--realtime`` (their name, whether given).
REALTIME_EXCLUDES = ("--self-calibrate", "--mcap", "--live")


def check_realtime(realtime: bool, given: dict[str, bool]) -> None:
    """Refuse the options ``--realtime`` cannot honour (one line)."""
    if not realtime:
        return
    bad = [name for name in REALTIME_EXCLUDES if given.get(name)]
    if bad:
        raise typer.BadParameter(f"--realtime does not go with {', '.join(bad)}")


def run_realtime_command(seq: Any, result: Any, detector: Any, judge: Any, cfg: Any) -> None:
    """Replay ``seq`` into ``result`` (a `ResultDir`) with progress; print what it measured."""
    from scanguard.apps.replay import format_ms as _ms
    from scanguard.apps.replay import run_realtime
    from scanguard.logging_utils import progress

    if cfg.compare:
        err_console.print(
            "--realtime: the main (guarded) instance alone; run without it for the comparisons",
            highlight=False,
        )
    n = len(seq) if cfg.max_scans is None else min(len(seq), cfg.max_scans)
    with result as tmp, progress(n, "scans (real time)") as advance:

        def on_scan(k: int, stats: dict[str, Any]) -> None:
            advance(1, status=f"{stats['processed']} processed, {stats['dropped']} dropped")

        res = run_realtime(seq, detector, tmp, config=cfg, baseline=judge, on_scan=on_scan)
        files = [result.final(p) for p in res.files]  # before the commit forgets the folder
    s, lat = res.stats, res.stats["latency_ms"]
    console.print(
        f"[bold]{res.name}[/bold] at the sensor's rate: {s['received']} scans, "
        f"{s['processed']} processed, {s['dropped']} dropped; latency median "
        f"{_ms(lat['median'])} / p99 {_ms(lat['p99'])} / max {_ms(lat['max'])} ms",
        highlight=False,
    )
    rel = res.errors.get("relations")
    if rel is not None:
        e = rel["all"]
        console.print(
            f"relations (all): {e['trans_mean_m']:.4f} m, {e['matched']} matched, "
            f"{e['unmatched']} unmatched",
            highlight=False,
        )
    for path in files:
        console.print(f"wrote {path}", highlight=False, soft_wrap=True)
