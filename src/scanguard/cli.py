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

# --- commands: simulate (sim) ----------------------------------------------------------------

# --- commands: dataset (dataset) -------------------------------------------------------------

# --- commands: train / evaluate / export (model) ---------------------------------------------

# --- commands: run / demo (pipeline) ---------------------------------------------------------
