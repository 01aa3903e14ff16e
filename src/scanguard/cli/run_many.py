"""``scanguard run-many``: the guarded SLAM loop over many recordings, one task each."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from scanguard.apps.config_merge import EXECUTORS, RUNTIMES, check_choice, run_config
from scanguard.cli.checks import AT_LEAST_ONE, NON_NEGATIVE, checked, command_record
from scanguard.cli.main import app, console, fail, guarded
from scanguard.cli.options import (
    Address,
    AllowOtherMatcher,
    Backend,
    Baseline,
    BaselineData,
    Config,
    Executor,
    FilterSeed,
    Lenient,
    Matcher,
    MaxScans,
    Model,
    Motion,
    Odometry,
    Out,
    Overwrite,
    Particles,
    Prior,
    RelationTolerance,
    Runtime,
    Workers,
)
from scanguard.errors import ConfigError


@app.command("run-many")
@guarded
@checked(seed=NON_NEGATIVE, workers=AT_LEAST_ONE)
def run_many(
    ctx: typer.Context,
    recordings: Annotated[
        str, typer.Argument(help="Folder (searched recursively) or glob pattern of recordings.")
    ],
    out: Out,
    executor: Executor = "local",
    address: Address = None,
    workers: Workers = None,
    lenient: Lenient = False,
    backend: Backend = None,
    runtime: Runtime = "onnx",
    odometry: Odometry = None,
    prior: Prior = None,
    motion: Motion = None,
    matcher: Matcher = None,
    particles: Particles = None,
    seed: FilterSeed = None,
    max_scans: MaxScans = None,
    relation_tolerance: RelationTolerance = None,
    model: Model = None,
    config: Config = None,
    baseline: Baseline = "auto",
    baseline_data: BaselineData = None,
    allow_other_matcher: AllowOtherMatcher = False,
    overwrite: Overwrite = False,
) -> None:
    """Run the guarded SLAM loop over many recordings (one task each); one merged table.

    Each recording gets OUT/<stem>/ (as `scanguard run`); a rerun skips complete ones; a
    failing recording is reported in OUT/results.csv and OUT/results.md, and the exit code
    is then 1. A folder that run-many did not create is refused without --overwrite.
    """
    from scanguard.apps.run_many import find_recordings
    from scanguard.fsutil import check_output_path
    from scanguard.runtime.executor import make_executor

    check_choice("--runtime", runtime, RUNTIMES)
    check_choice("--executor", executor, EXECUTORS)
    cfg = run_config(
        config,
        backend=backend,
        odometry=odometry,
        prior=prior,
        motion=motion,
        matcher=matcher,
        particles=particles,
        seed=seed,
        max_scans=max_scans,
        allow_other_matcher=allow_other_matcher,
        relation_tolerance=relation_tolerance,
    )
    if cfg.relations is not None:
        raise ConfigError(
            "run-many: the config names one relations file for every recording; drop "
            "'relations' (each recording uses <stem>.relations next to it)"
        )
    pool = make_executor(executor, address=address, workers=workers)
    out_path = check_output_path(out, kind="dir")
    found = find_recordings(recordings, exclude=out_path)
    console.print(f"{len(found)} recordings, executor {executor}", highlight=False)
    options = {
        "model": model,
        "runtime": runtime,
        "baseline": baseline,
        "lenient": lenient,
        "overwrite": overwrite,
    }
    _run_each(ctx, found, (out_path, Path(out)), cfg, pool, baseline_data=baseline_data, **options)


def _run_each(
    ctx: typer.Context,
    found: list[Path],
    out: tuple[Path, Path],
    cfg: Any,
    pool: Any,
    **options: Any,
) -> None:
    """`scale.run_many` with one line per finished recording; exit 1 when any failed.

    ``out`` is the checked output folder and the one given (shown in messages).
    """
    from rich.markup import escape

    from scanguard.apps.run_many import run_many as run_many_

    record = command_record(ctx)

    def show(res: Any) -> None:
        tail = f": {res.error}" if res.error else ""
        console.print(
            f"{res.status:8s} {escape(str(res.recording))}{escape(tail)}",
            highlight=False,
            soft_wrap=True,
        )

    dest, given = out
    results = run_many_(
        found,
        dest,
        cfg,
        pool,
        record={"command": record["command"], "cwd": record["cwd"]},
        on_result=show,
        **options,
    )
    console.print(
        f"table in [bold]{escape(str(given / 'results.md'))}[/bold] (and results.csv)",
        highlight=False,
    )
    failed = sum(r.status == "failed" for r in results)
    if failed:
        fail(f"{failed} of {len(results)} recordings failed (see {given / 'results.md'})")
