"""``scanguard evaluate``: the paper's Table 2 per environment, with the baselines."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Annotated, Any

import typer

from scanguard.apps.config_merge import EXECUTORS, RUNTIMES, check_choice
from scanguard.apps.report import evaluation_tables
from scanguard.cli.checks import command_record, result_dir
from scanguard.cli.main import app, console, fail, guarded
from scanguard.cli.options import (
    Address,
    Data,
    Executor,
    Model,
    OptionalOut,
    Overwrite,
    Runtime,
    Split,
    Workers,
)
from scanguard.cli.render import print_tables
from scanguard.errors import ConfigError, ScanGuardError


@app.command()
@guarded
def evaluate(
    ctx: typer.Context,
    data: Data,
    model: Model = None,
    out: OptionalOut = None,
    split: Split = ["test", "heldout"],  # noqa: B006 - typer never mutates it
    environment: Annotated[
        list[str],
        typer.Option(
            "--environment", "-e", metavar="NAME", help="Only these environments (repeatable)."
        ),
    ] = [],  # noqa: B006
    baselines: Annotated[
        str,
        typer.Option(
            "--baselines",
            metavar="NAMES",
            help="'all', 'none' or a comma list (residual,overlap,...).",
        ),
    ] = "all",
    baseline_data: Annotated[
        list[str],
        typer.Option(
            "--baseline-data",
            metavar="PATH",
            help="Store whose train split fits the baselines (default: --data).",
        ),
    ] = [],  # noqa: B006
    runtime: Runtime = "torch",
    overwrite: Overwrite = False,
    per_store: Annotated[
        bool,
        typer.Option(
            "--per-store",
            help="Evaluate each --data store on its own (one task each) into OUT/<name>/, "
            "plus one merged OUT/results.csv; resumable.",
        ),
    ] = False,
    executor: Executor = "local",
    address: Address = None,
    workers: Workers = None,
) -> None:
    """Paper Table 2 per environment (fault = positive) + baselines; ROC/confusion PNGs.

    Writes results.json, results.csv, roc.png, reliability.png, ... into OUT when given.
    --executor, --address and --workers apply to --per-store.
    """
    from rich.markup import escape

    from scanguard.detect.evaluate import evaluate_store

    check_choice("--runtime", runtime, RUNTIMES)
    names = _baseline_names(baselines)
    options: dict[str, Any] = {
        "splits": None if "all" in split else split,
        "environments": environment or None,
        "baselines": names,
        "baseline_store": (baseline_data if len(baseline_data) > 1 else baseline_data[0])
        if baseline_data
        else None,
        "backend": runtime,
    }
    if per_store:
        _evaluate_per_store(ctx, data, out, executor, address, workers, model, options)
        return
    if executor != "local" or address is not None or workers is not None:
        raise ConfigError("--executor, --address and --workers apply to --per-store only")
    result = result_dir(ctx, out, overwrite) if out else None
    with result if result is not None else contextlib.nullcontext() as tmp:
        try:
            res = evaluate_store(model, data if len(data) > 1 else data[0], tmp, **options)
        except ScanGuardError as exc:
            _explain_missing_train_split(exc, names, baseline_data)
            raise
    print_tables(evaluation_tables(res.rows))
    if out:
        console.print(
            f"results in [bold]{escape(out)}[/bold] (results.json, results.csv, roc.png, "
            "reliability.png, ...)"
        )


def _baseline_names(baselines: str) -> list[str] | None:
    """The baselines of ``--baselines`` (None: all of them)."""
    if baselines == "all":
        return None
    if baselines == "none":
        return []
    return [b.strip() for b in baselines.split(",") if b.strip()]


def _explain_missing_train_split(
    exc: ScanGuardError, names: list[str] | None, baseline_data: list[str]
) -> None:
    """A store without a train split cannot fit the baselines: say what to give instead."""
    text = str(exc)
    if (
        "no labelled pairs" in text
        and "train" in text
        and names != []
        and not baseline_data
        and "--baseline" not in text
    ):
        raise ConfigError(
            f"{text}; the baselines are fitted on a train split: give "
            "--baseline-data STORE (e.g. a simulated build) or --baselines none"
        ) from exc


def _evaluate_per_store(
    ctx: typer.Context,
    data: list[str],
    out: str | None,
    executor: str,
    address: str | None,
    workers: int | None,
    model: str | None,
    options: dict[str, Any],
) -> None:
    """``evaluate --per-store``: one task per store, merged table (`scale.evaluate_many`)."""
    from rich.markup import escape

    from scanguard.apps.evaluate_many import evaluate_many
    from scanguard.runtime.executor import make_executor

    if not out:
        raise ConfigError("--per-store needs --out (a folder per store plus the merged table)")
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    check_choice("--executor", executor, EXECUTORS)
    pool = make_executor(executor, address=address, workers=workers)
    record = command_record(ctx)

    def show(res: Any) -> None:
        tail = f": {res.error}" if res.error else ""
        console.print(
            f"{res.status:8s} {escape(str(res.store))}{escape(tail)}",
            highlight=False,
            soft_wrap=True,
        )

    results = evaluate_many(
        data,
        out,
        pool,
        record={"command": record["command"], "cwd": record["cwd"]},
        on_result=show,
        overwrite=bool(ctx.params.get("overwrite")),  # a user's folder only with --overwrite
        model=model,
        **options,
    )
    console.print(
        f"table in [bold]{escape(str(Path(out) / 'results.md'))}[/bold] (and results.csv)",
        highlight=False,
    )
    failed = sum(r.status == "failed" for r in results)
    if failed:
        fail(f"{failed} of {len(results)} stores failed (see {Path(out) / 'results.md'})")
