"""``scanguard simulate``: a crowded LiDAR recording with exact ground truth, as a ROS 2 bag."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from scanguard.cli.checks import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    bag_output,
    checked,
    outputs,
    png_output,
)
from scanguard.cli.main import app, console, guarded
from scanguard.cli.options import OverwriteRecording
from scanguard.errors import ConfigError


@app.command()
@guarded
@checked(
    seed=NON_NEGATIVE,
    duration=POSITIVE,
    stride=AT_LEAST_ONE,
    scan_rate=POSITIVE,
    people=NON_NEGATIVE,
)
@outputs(output=bag_output, preview=png_output)  # before the simulation, not after it
def simulate(
    scenario: Annotated[
        str,
        typer.Option(
            "--scenario",
            "-s",
            metavar="NAME",
            help="lobby, corridor, glass, hall, office (the paper's E1-5), a GMapping or "
            "closure trap (crowd_follow, mixed_loop, twin_rooms, ...), office_slip (the demo), "
            "or a YAML file.",
        ),
    ] = "lobby",
    seed: Annotated[
        int, typer.Option("--seed", help="Seed of all randomness (layout, people, noise).")
    ] = 0,
    duration: Annotated[float, typer.Option("--duration", "-d", help="Simulated seconds.")] = 60.0,
    output: Annotated[
        str | None,
        typer.Option(
            "--output", "-o", metavar="PATH", help="ROS 2 bag to write (*.mcap = one MCAP file)."
        ),
    ] = None,
    preview: Annotated[
        str | None,
        typer.Option(
            "--preview", metavar="PATH", help="PNG with the world, robot path and people tracks."
        ),
    ] = None,
    stride: Annotated[int | None, typer.Option("--stride", help="Keep every k-th scan.")] = None,
    scan_rate: Annotated[float | None, typer.Option("--scan-rate", help="Scan rate (Hz).")] = None,
    people: Annotated[int | None, typer.Option("--people", help="Number of pedestrians.")] = None,
    sensor: Annotated[
        str | None,
        typer.Option(
            "--sensor", metavar="NAME", help="rplidar_a3, sick_lms, hokuyo_utm30lx or pr2_base."
        ),
    ] = None,
    set_: Annotated[
        list[str],
        typer.Option(
            "--set",
            metavar="KEY=VALUE",
            help="Override any config value: --set people.carts=3 (repeatable).",
        ),
    ] = [],  # noqa: B006 - typer never mutates it
    overwrite: OverwriteRecording = False,
) -> None:
    """Simulate a crowded LiDAR recording with exact ground truth and write it as a ROS 2 bag.

    The bag is streamed to disk while the simulation runs (constant memory) under a temporary
    name and renamed into place at the end. The scenario, the run's size and every output are
    checked before the simulation starts.
    """
    import contextlib

    from scanguard.sim import parse_overrides, plan_simulation, simulate_run
    from scanguard.sim.limits import check_seed
    from scanguard.sim.output import BagStreamWriter

    if output is None and preview is None:
        raise ConfigError("nothing to do: give --output (bag) and/or --preview (PNG)")
    check_seed(seed)
    overrides = parse_overrides(set_)
    options = {
        "stride": stride,
        "scan_rate_hz": scan_rate,
        "people__count": people,
        "sensor__model": sensor,
    }
    overrides.update({k: v for k, v in options.items() if v is not None})
    # everything that can be refused is refused before the simulation starts
    cfg, seconds, plan = plan_simulation(scenario, duration=duration, keep_scans=False, **overrides)
    bag, cfg_dest, png = _destinations(output, preview, plan.bag_bytes, overwrite)
    with contextlib.ExitStack() as stack:
        writer = None if bag is None else stack.enter_context(BagStreamWriter(bag))
        res = simulate_run(
            cfg, seed=seed, duration=seconds, progress=True, sink=writer, keep_scans=False
        )
    written = _write_extras(res, (output, cfg_dest), (preview, png))
    console.print(_result_table(res, seed, written))


def _destinations(
    output: str | None, preview: str | None, bag_bytes: float, overwrite: bool
) -> tuple[Any, ...]:
    """The checked bag, scenario YAML and preview paths (None where not asked for)."""
    from scanguard.fsutil import check_output_path
    from scanguard.sim.output import check_bag_output, check_free_space, check_preview_output

    bag = cfg_dest = png = None
    if output is not None:
        bag = check_bag_output(output, overwrite=overwrite)
        given = Path(output)
        cfg_dest = check_output_path(given.parent / f"{given.stem}.scenario.yaml", "file")
        check_free_space(bag, bag_bytes)
    if preview is not None:
        png = check_preview_output(preview, overwrite=overwrite)
    return bag, cfg_dest, png


def _write_extras(res: Any, bag: tuple[Any, Any], png: tuple[Any, Any]) -> list[str]:
    """Write the scenario YAML next to the bag and the preview; the files written.

    ``bag`` is ``(--output, checked scenario YAML path)``, ``png`` ``(--preview, checked path)``.
    """
    from scanguard.config import save_config

    (output, cfg_dest), (preview, png_dest) = bag, png
    written = []
    if output is not None and cfg_dest is not None:
        save_config(res.config, cfg_dest.parent, name=cfg_dest.name)
        written += [str(output), str(Path(str(output)).with_name(cfg_dest.name))]
    if png_dest is not None:
        from scanguard.sim.preview import save_preview

        save_preview(res, png_dest)
        written.append(str(preview))
    return written


def _result_table(res: Any, seed: int, written: list[str]) -> Any:
    import numpy as np
    from rich.markup import escape
    from rich.table import Table

    sensor_info = res.sequence.sensor
    assert sensor_info is not None  # simulate_run always sets it
    steps = np.diff(res.robot_path[:: res.config.stride, :2], axis=0)
    table = Table(title=f"simulated {res.config.name} (seed {seed})", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row(
        "scans",
        f"{res.n_kept} at {sensor_info.rate_hz or 0:.1f} Hz, {sensor_info.n_beams} beams",
    )
    table.add_row("sensor", f"{sensor_info.name}, {sensor_info.fov_deg:.0f} deg")
    table.add_row("agents", str(res.sequence.metadata["n_people"]))
    table.add_row("robot path", f"{np.hypot(steps[:, 0], steps[:, 1]).sum():.1f} m")
    table.add_row("inf beams", f"{100 * res.inf_fraction:.1f} %")
    table.add_row("written", escape("\n".join(written)))
    return table
