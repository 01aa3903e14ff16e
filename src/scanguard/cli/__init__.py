"""Command-line interface: one module per command group; they parse, call the library, print.

``scanguard.cli:app`` is the console script. Importing this package registers every command
on it (each module adds its commands to `scanguard.cli.main.app`).
"""

from scanguard.cli import (
    calibrate,
    dataset,
    evaluate,
    export,
    info,
    run,
    run_many,
    simulate,
    train,
)
from scanguard.cli.main import app

__all__ = [
    "app",
    "calibrate",
    "dataset",
    "evaluate",
    "export",
    "info",
    "run",
    "run_many",
    "simulate",
    "train",
]
