"""``scanguard run``, ``demo`` and ``run-many``: the guarded SLAM loop over recordings."""

from __future__ import annotations

import os
from typing import Annotated, Any

import typer

from scanguard.apps.config_merge import RUNTIMES, check_choice, check_odom_topic, run_config
from scanguard.apps.report import pipeline_tables
from scanguard.apps.self_calibrate import SelfCalibration
from scanguard.cli.checks import NON_NEGATIVE, Bound, checked, result_dir
from scanguard.cli.main import app, console, err_console, guarded
from scanguard.cli.options import (
    AllowOtherMatcher,
    Backend,
    Baseline,
    BaselineData,
    Config,
    Corrected,
    FilterSeed,
    Lenient,
    Live,
    LiveHost,
    LivePort,
    MapInterval,
    Matcher,
    MaxScans,
    Mcap,
    Model,
    Motion,
    NoCompare,
    Odometry,
    OdomTopic,
    Out,
    Overwrite,
    Particles,
    Prior,
    Reference,
    ReferenceTopic,
    RelationsFile,
    RelationTolerance,
    Runtime,
    ScanTopic,
    SelfCalibrate,
)
from scanguard.cli.realtime import Realtime, check_realtime, run_realtime_command
from scanguard.cli.render import exit_on_partial_relations, print_tables, scan_progress

#: Bounds of the view options (``--port`` 0: any free port).
VIEW_BOUNDS = {"port": Bound(low=0, high=65535), "map_interval": NON_NEGATIVE}

OUTPUTS = "trajectory.tum, map.pgm/.yaml (the main result), summary.md, metrics.json, "
OUTPUTS += "maps_side_by_side.png, trajectories.png, map_unguarded.*, "


@app.command()
@guarded
@checked(seed=NON_NEGATIVE, **VIEW_BOUNDS)  # --max-scans, --particles: checked by RunConfig
def run(
    ctx: typer.Context,
    recording: Annotated[str, typer.Argument(help="Bag, bag folder or CARMEN log.")],
    out: Out = "scanguard-run",
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    reference_topic: ReferenceTopic = None,
    reference: Reference = None,
    lenient: Lenient = False,
    corrected: Corrected = None,
    backend: Backend = None,
    runtime: Runtime = "onnx",
    odometry: Odometry = None,
    prior: Prior = None,
    motion: Motion = None,
    matcher: Matcher = None,
    particles: Particles = None,
    seed: FilterSeed = None,
    relations: RelationsFile = None,
    max_scans: MaxScans = None,
    relation_tolerance: RelationTolerance = None,
    no_compare: NoCompare = False,
    model: Model = None,
    self_calibrate: SelfCalibrate = False,
    config: Config = None,
    baseline: Baseline = "auto",
    baseline_data: BaselineData = None,
    overwrite: Overwrite = False,
    allow_other_matcher: AllowOtherMatcher = False,
    mcap: Mcap = False,
    live: Live = False,
    host: LiveHost = "127.0.0.1",
    port: LivePort = 8765,
    map_interval: MapInterval = 5.0,
    realtime: Realtime = False,
) -> None:
    """Run the guarded SLAM loop over a recording; write trajectories, maps and metrics."""
    from scanguard.io import read_sequence

    check_choice("--runtime", runtime, RUNTIMES)
    check_realtime(realtime, {"--self-calibrate": self_calibrate, "--mcap": mcap, "--live": live})
    view = _view(mcap, live, host, port, map_interval)
    cfg = run_config(
        config,
        backend=backend,
        odometry=odometry,
        prior=prior,
        motion=motion,
        matcher=matcher,
        particles=particles,
        seed=seed,
        relations=relations,
        max_scans=max_scans,
        allow_other_matcher=allow_other_matcher,
        relation_tolerance=relation_tolerance,
        compare=not no_compare,
    )
    result = result_dir(ctx, out, overwrite)  # before reading the recording
    _before_reading(recording, cfg)
    seq = read_sequence(
        recording,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
        reference=reference,
        reader_options=None if corrected is None else {"corrected": corrected},
        lenient=lenient,
        max_scans=cfg.max_scans,  # stop reading there: a long recording is never all read
    )
    check_odom_topic(seq, odom_topic, cfg)
    if realtime:
        detector, judge, _ = _guard_models(model, cfg, baseline, baseline_data, runtime)
        run_realtime_command(seq, result, detector, judge, cfg)
        return
    self_cal = SelfCalibration(recording, scan_topic, odom_topic) if self_calibrate else None
    res = _pipeline_execute(
        seq, result, model, cfg, baseline, baseline_data, runtime, view, self_cal
    )
    _pipeline_report(res, out)
    exit_on_partial_relations(res)


def _before_reading(recording: str, cfg: Any) -> None:
    """What a run sets up before it reads its recording.

    The relations file ``<stem>.relations`` next to the recording when none was given, and the
    worker process a long run's instances will use, started now so that it loads meanwhile.
    """
    from scanguard.apps.loop_setup import prestart_instance_worker
    from scanguard.apps.run_relations import find_relations

    prestart_instance_worker(cfg)
    if cfg.relations is None:
        found = find_relations(recording)
        if found is not None:
            console.print(
                f"relations: {found} (found next to the recording)",
                highlight=False,
                soft_wrap=True,
            )
            cfg.relations = str(found)


def _view(mcap: bool, live: bool, host: str, port: int, map_interval: float) -> Any:
    """The checked `scanguard.apps.viz_sink.ViewOptions` (``--live`` needs the viz extra)."""
    from scanguard.apps.viz_sink import ViewOptions

    view = ViewOptions(mcap, live, host, port, map_interval)
    view.check()
    return view


@app.command()
@guarded
@checked(seed=NON_NEGATIVE, **VIEW_BOUNDS)
def demo(
    ctx: typer.Context,
    out: Out = "scanguard-demo",
    fast: Annotated[
        bool,
        typer.Option("--fast", help="A few dozen scans (for CI; also when the CI env var is set)."),
    ] = False,
    seed: Annotated[int, typer.Option("--seed", help="Simulation seed.")] = 7,
    backend: Backend = None,
    runtime: Runtime = "onnx",
    particles: Particles = None,
    model: Model = None,
    baseline: Baseline = "auto",
    baseline_data: BaselineData = None,
    overwrite: Overwrite = False,
    mcap: Mcap = False,
    live: Live = False,
    host: LiveHost = "127.0.0.1",
    port: LivePort = 8765,
    map_interval: MapInterval = 5.0,
    config: Config = None,
    no_compare: NoCompare = False,
) -> None:
    """Simulate the demo scene (an office whose wheels slip) and run the guarded SLAM on it."""
    from scanguard.apps.demo import DEMO_GMAPPING_LSKIP, DEMO_SCENARIO, demo_sequence

    check_choice("--runtime", runtime, RUNTIMES)
    view = _view(mcap, live, host, port, map_interval)
    cfg = run_config(config, backend=backend, particles=particles, compare=not no_compare)
    cfg.gmapping = cfg.gmapping.model_copy(update={"lskip": DEMO_GMAPPING_LSKIP})
    result = result_dir(ctx, out, overwrite)  # before simulating
    fast = fast or bool(os.environ.get("CI"))
    with err_console.status(f"simulating the {DEMO_SCENARIO} scene"):
        seq = demo_sequence(fast=fast, seed=seed)
    res = _pipeline_execute(seq, result, model, cfg, baseline, baseline_data, runtime, view)
    _pipeline_report(res, out)


def _pipeline_execute(
    seq: Any,
    result: Any,
    model: Any,
    cfg: Any,
    baseline: str = "auto",
    baseline_data: str | None = None,
    runtime: str = "onnx",
    view: Any = None,
    self_cal: Any = None,
) -> Any:
    """Load the detector and the baseline, run the loop into ``result`` (a `ResultDir`).

    ``view`` (`scanguard.apps.viz_sink.ViewOptions`): the MCAP file and the live view.
    ``self_cal`` (`scanguard.apps.self_calibrate.SelfCalibration`): recalibrate the model on
    the recording first, into the result folder.
    """
    from scanguard.apps.run import run_recording
    from scanguard.apps.viz_sink import ViewOptions, open_view

    detector, judge, judge_info = _guard_models(model, cfg, baseline, baseline_data, runtime)
    n = len(seq) if cfg.max_scans is None else min(len(seq), cfg.max_scans)
    view = view or ViewOptions()
    with result as tmp:
        learned = None
        if self_cal is not None:
            with err_console.status("self-calibration: a first pass, then the labels"):
                detector, learned = self_cal.detector(tmp / "self_calibration", model, cfg, runtime)
        noise, grid = cfg.odometry_noise, cfg.guard.grid
        with (
            scan_progress(n) as on_step,
            open_view(view, tmp, grid=grid, odometry_noise=noise) as observer,
        ):
            res = run_recording(
                seq,
                detector,
                tmp,
                config=cfg,
                baseline=judge,
                on_step=on_step,
                baseline_info=judge_info,
                observer=observer,
                self_calibration=learned,
            )
        if view.mcap:
            res.files.append(tmp / "result.mcap")
        res.files = [result.final(p) for p in res.files]  # before the commit forgets the folder
    return res


def _guard_models(
    model: Any, cfg: Any, baseline: str, baseline_data: str | None, runtime: str
) -> tuple[Any, Any, str]:
    """The CNN detector, the baseline gate's detector and its description (printed)."""
    from scanguard.apps.run_baseline import resolve_baseline
    from scanguard.detect.detector import FaultDetector

    check_choice("--runtime", runtime, RUNTIMES)
    detector = FaultDetector.load(model, backend=runtime, matcher=cfg.matcher)  # type: ignore[arg-type]
    with err_console.status("preparing the baseline gate"):
        judge, judge_info = resolve_baseline(baseline, baseline_data, cfg.matcher)
    console.print(f"baseline gate: {judge_info}", highlight=False, soft_wrap=True)
    return detector, judge, judge_info


def _pipeline_report(res: Any, out: Any) -> None:
    """Print a run's headline, the guard's counts and the tables of `pipeline_tables`."""
    from rich.markup import escape

    from scanguard.apps.run_headline import relations_used_lines
    from scanguard.apps.run_result import judged_text

    console.print(
        f"[bold]{escape(str(res.name))}[/bold]: {res.n_scans} scans; odometry: "
        f"{res.odometry_source}; "
        f"matcher: {res.matcher}; back end: {res.backend}; reference: "
        f"{res.reference_kind or 'none'}",
        highlight=False,
    )
    console.print(f"guard: {judged_text(res.counts)}", highlight=False)
    for line in relations_used_lines(res):
        console.print(line[2:], highlight=False, soft_wrap=True)
    print_tables(pipeline_tables(res), blank_before=True)
    console.print(
        f"outputs in [bold]{escape(str(out))}[/bold] ({OUTPUTS}trajectory_<comparison>.tum)",
        highlight=False,
    )
