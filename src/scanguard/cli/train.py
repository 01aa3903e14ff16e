"""``scanguard train``: train the fault-detection CNN."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any

import typer

from scanguard.apps.report import training_table
from scanguard.cli.checks import AT_LEAST_ONE, NON_NEGATIVE, checked, result_dir
from scanguard.cli.main import app, console, guarded
from scanguard.cli.options import Config, Data, Out, Overwrite
from scanguard.cli.render import rich_table

PRESETS = "paper|compact|multiscale|cnn+metrics|cnn+metrics+odometry|compact128|tiny"


@app.command()
@guarded
@checked(epochs=AT_LEAST_ONE, max_train=AT_LEAST_ONE, seed=NON_NEGATIVE, threads=AT_LEAST_ONE)
def train(
    ctx: typer.Context,
    data: Data,
    out: Out,
    config: Config = None,
    preset: Annotated[
        str | None, typer.Option("--preset", metavar="NAME", help=f"{PRESETS}.")
    ] = None,
    epochs: Annotated[
        int | None, typer.Option("--epochs", help="Override the epoch count.")
    ] = None,
    max_train: Annotated[
        int | None, typer.Option("--max-train", help="Seeded training subset.")
    ] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Override the seed.")] = None,
    threads: Annotated[int | None, typer.Option("--threads", help="Torch threads.")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Train the fault-detection CNN (best epoch on the validation split).

    Writes OUT/model.pt, curves.png, history.json and config.yaml. Under torchrun
    (torchrun --nproc-per-node N --no-python scanguard train ...) the processes train one
    model with DistributedDataParallel (gloo on CPU, nccl with CUDA) on the same global
    batch; rank 0 writes the output.
    """
    # idle OpenMP workers must sleep, not spin: the machine is shared with other jobs
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from rich.markup import escape

    from scanguard.detect.distributed import init_distributed
    from scanguard.detect.train import train as run_training
    from scanguard.detect.train_config import TrainConfig

    cfg = TrainConfig.from_yaml(config) if config else TrainConfig()
    updates: dict[str, Any] = {}
    if preset is not None:
        updates.update(preset=preset, model=None, style=None)
    for key, val in (("epochs", epochs), ("max_train", max_train), ("seed", seed)):
        if val is not None:
            updates[key] = val
    if threads is not None:
        updates["threads"] = threads
    if updates:
        cfg = TrainConfig.from_dict({**cfg.model_dump(), **updates}, source="command line")
    rank, _world = init_distributed()  # under torchrun: DDP, rank 0 writes
    if rank != 0:
        run_training(cfg, data if len(data) > 1 else data[0], out)
        return
    result = result_dir(ctx, out, overwrite)
    with result as tmp:
        res = run_training(cfg, data if len(data) > 1 else data[0], tmp)
    best = res.checkpoint["info"]["best_epoch"]
    preset_name = res.checkpoint["model_config"]["preset"]
    console.print(rich_table(training_table(preset_name, res.history, best)))
    console.print(
        f"best epoch {best}, threshold {res.checkpoint['threshold']:.3f}; "
        f"model in [bold]{escape(str(Path(out) / 'model.pt'))}[/bold] (curves.png, "
        "history.json, config.yaml)"
    )
