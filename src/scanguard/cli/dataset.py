"""``scanguard dataset build|stats|export-png|merge``: labelled scan-pair datasets."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from scanguard.apps.config_merge import EXECUTORS, check_choice
from scanguard.apps.report import build_table, stats_table
from scanguard.cli.checks import AT_LEAST_ONE, NON_NEGATIVE, Bound, checked, result_dir
from scanguard.cli.main import app, console, fail, guarded
from scanguard.cli.options import (
    Address,
    Config,
    Executor,
    MaxScans,
    OdomTopic,
    Overwrite,
    Recordings,
    Reference,
    ReferenceTopic,
    ScanTopic,
    Workers,
)
from scanguard.cli.render import rich_table
from scanguard.cli.usage import UnixTyper
from scanguard.errors import ConfigError

dataset_app = UnixTyper(
    help="Build, inspect and export labelled scan-pair datasets.", no_args_is_help=True
)
app.add_typer(dataset_app, name="dataset")

Stores = Annotated[
    list[str], typer.Argument(metavar="STORE", help="Dataset directories and/or pair files.")
]
INITIAL_GUESSES = ("identity", "odometry", "simulated_odometry", "auto")


@dataset_app.command("build")
@guarded
@checked(max_scans=Bound(low=2), workers=AT_LEAST_ONE)
def dataset_build(
    out: Annotated[
        str, typer.Option("--out", "-o", metavar="PATH", help="Build directory (resumable).")
    ],
    config: Config = None,
    recording: Recordings = [],  # noqa: B006 - typer never mutates it
    reference: Reference = None,
    matcher: Annotated[
        str | None,
        typer.Option("--matcher", metavar="NAME", help="Override the config's matcher."),
    ] = None,
    initial: Annotated[
        str | None,
        typer.Option(
            "--initial",
            metavar="NAME",
            help="Recordings: identity|odometry|simulated_odometry|auto.",
        ),
    ] = None,
    max_scans: MaxScans = None,
    workers: Workers = None,
    executor: Executor = "local",
    address: Address = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Rebuild files of another config.")
    ] = False,
    scan_topic: ScanTopic = None,
    odom_topic: OdomTopic = None,
    reference_topic: ReferenceTopic = None,
) -> None:
    """Simulate + match + label (with --config), or label recordings (with --recording).

    One task per sequence or recording, each writing its own shard; a rerun resumes. A
    recording that fails is reported, the others finish, and the exit code is then 1. The
    --reference, --max-scans and --*-topic options apply to --recording.
    """
    import time

    from scanguard.dataset import build as build_mod
    from scanguard.dataset import build_dataset
    from scanguard.fsutil import check_output_path
    from scanguard.runtime.executor import make_executor

    check_output_path(out, "dir")  # before any work: a file, a device, unwritable
    topics = (scan_topic, odom_topic, reference_topic)
    if any(t is not None for t in topics) and not recording:
        raise ConfigError("--scan-topic/--odom-topic/--reference-topic apply to --recording only")
    cfg = _dataset_config(config, matcher, initial)
    check_choice("--executor", executor, EXECUTORS)
    pool = make_executor(executor, address=address, workers=workers)
    t0 = time.perf_counter()
    if recording:
        # all recordings in one call: registered as pending together, counted together;
        # failures are reported, the others finish
        summary = build_mod.build_from_recordings(
            list(recording),
            out,
            cfg,
            reference=reference,
            initial_guess=initial,  # type: ignore[arg-type]  # checked above
            max_scans=max_scans,
            overwrite=overwrite,
            executor=pool,
            scan_topic=scan_topic,
            odom_topic=odom_topic,
            reference_topic=reference_topic,
        )
    else:
        if not config:
            raise ConfigError("give --config (simulated build) or --recording PATH")
        # local: one worker builds in this process (progress per pair), more in a pool
        summary = build_dataset(
            cfg,
            out,
            overwrite=overwrite,
            workers=getattr(pool, "workers", None) or 1,  # capped at the CPUs
            executor=pool if executor == "ray" else None,
        )
    _report_build(out, summary, time.perf_counter() - t0)


def _dataset_config(config: str | None, matcher: str | None, initial: str | None) -> Any:
    """The `DatasetConfig` of ``--config`` (or the defaults) and ``--matcher``; checks --initial."""
    from scanguard.dataset import DatasetConfig

    cfg = DatasetConfig.from_yaml(config) if config else DatasetConfig()
    if matcher:
        cfg = cfg.model_copy(update={"matcher": matcher})
        cfg = DatasetConfig.from_dict(cfg.model_dump(), source="--matcher")
    if initial is not None and initial not in INITIAL_GUESSES:
        raise ConfigError(f"--initial must be one of {', '.join(INITIAL_GUESSES)}, got {initial!r}")
    return cfg


def _report_build(out: str, summary: Any, seconds: float) -> None:
    """The build's table and its failures (then exit code 1)."""
    from rich.markup import escape

    title = f"{out}: {len(summary.built)} built, {len(summary.skipped)} resumed"
    console.print(rich_table(build_table(title, summary)))
    console.print(f"done in {seconds:.1f} s")
    for what, error in summary.failed.items():
        console.print(f"failed   {escape(what)}: {escape(error)}", highlight=False, soft_wrap=True)
    if summary.failed:
        fail(f"{len(summary.failed)} failed (a rerun of the same command retries what can succeed)")


@dataset_app.command("stats")
@guarded
def dataset_stats(
    ctx: typer.Context,
    store: Stores,
    out: Annotated[
        str | None,
        typer.Option(
            "--out",
            "-o",
            metavar="PATH",
            help="Histogram/JSON directory (default: <first store>/stats).",
        ),
    ] = None,
    overwrite: Overwrite = False,
) -> None:
    """Per-environment normal/fault/ambiguous counts and error histograms (PNG)."""
    from scanguard.dataset import PairStore, write_stats

    first = Path(store[0])
    dest = Path(out) if out else (first if first.is_dir() else first.parent) / "stats"
    # written as a whole; a user's folder given with -o only with --overwrite
    result = result_dir(ctx, out, overwrite) if out else None
    ps = PairStore.open(store)
    if result is None:  # the default folder: scanguard's own place in the store
        result = result_dir(ctx, str(dest), True)
    with result as tmp:
        rows, _js = write_stats(ps, tmp)
    console.print(rich_table(stats_table(f"{len(ps)} pairs", rows)))
    console.print(f"histograms and stats.json in {dest}")


@dataset_app.command("export-png")
@guarded
@checked(per_class=AT_LEAST_ONE, size=AT_LEAST_ONE, seed=NON_NEGATIVE)
def dataset_export_png(
    ctx: typer.Context,
    store: Stores,
    out: Annotated[
        str, typer.Option("--out", "-o", metavar="PATH", help="Root of <env>/<class>/*.png.")
    ],
    per_class: Annotated[
        int | None,
        typer.Option("--per-class", "-n", help="At most N images per environment and class."),
    ] = None,
    kind: Annotated[
        str, typer.Option("--style", metavar="NAME", help="paper | occupancy | metric.")
    ] = "paper",
    size: Annotated[int, typer.Option("--size", help="Image side (px).")] = 256,
    ambiguous: Annotated[
        bool, typer.Option("--ambiguous", help="Also export ambiguous pairs.")
    ] = False,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the per-class subsample.")] = 0,
    overwrite: Overwrite = False,
) -> None:
    """Write pair images in the paper's folder layout (<env>/normal, <env>/fault)."""
    from scanguard.dataset import PairStore
    from scanguard.detect.images import export_png
    from scanguard.detect.render import RenderStyle

    result = result_dir(ctx, out, overwrite)
    style = RenderStyle.from_dict({"kind": kind, "size": size}, source="--style/--size")
    ps = PairStore.open(store)
    with result as tmp:
        written = export_png(
            ps,
            tmp,
            style,
            per_class=per_class,
            include_ambiguous=ambiguous,
            seed=seed,
            progress=True,
        )
    console.print(f"images in {out}", highlight=False)
    for env, counts in written.items():
        console.print(f"{env}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))


@dataset_app.command("merge")
@guarded
def dataset_merge(
    sources: Stores,
    out: Annotated[
        str, typer.Option("--out", "-o", metavar="PATH", help="Merged dataset directory.")
    ],
    overwrite: Overwrite = False,
) -> None:
    """Copy several builds into one dataset directory with one manifest.

    An existing dataset (or any folder an earlier merge did not write) is refused unless
    --overwrite is given; the result of an earlier merge is replaced as a whole.
    """
    from scanguard.dataset import PairStore, merge_stores

    dest = merge_stores(sources, out, overwrite=overwrite)
    console.print(f"{dest}: {len(PairStore.open(dest))} pairs")
