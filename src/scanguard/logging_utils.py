"""Logging and progress set-up shared by the CLI and the library.

Library modules only ever call ``logging.getLogger`` and, for long loops, `progress`: a
progress bar on a terminal, and a log line every 10 % when stderr is not a terminal (a log
file or a CI job never fills with bar redraws).
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from collections.abc import Callable, Iterator
from typing import TextIO

#: Format of log lines when stderr is not a terminal.
PLAIN_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is at the time of each record."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, value: TextIO) -> None:
        pass


def stderr_is_terminal() -> bool:
    """Whether stderr is an interactive terminal (rich's rules: ``FORCE_COLOR``, ``TTY_*``)."""
    from rich.console import Console

    return Console(stderr=True).is_terminal


def configure_logging(verbose: bool = False) -> None:
    """Route logs to stderr: scanguard's at INFO (DEBUG when ``verbose``), others' warnings.

    On a terminal the lines go through rich; otherwise they are plain single lines with a
    time stamp, never wrapped to the terminal width.
    """
    handler: logging.Handler
    if stderr_is_terminal():
        from rich.console import Console
        from rich.logging import RichHandler

        handler = RichHandler(console=Console(stderr=True), show_path=False, rich_tracebacks=False)
        handler.setFormatter(logging.Formatter("%(message)s"))
    else:
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter(PLAIN_FORMAT, datefmt="%H:%M:%S"))
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, handlers=[handler], force=True
    )
    logging.getLogger("scanguard").setLevel(logging.DEBUG if verbose else logging.INFO)


@contextlib.contextmanager
def progress(
    total: int | None,
    description: str,
    *,
    logger: logging.Logger | None = None,
    enabled: bool = True,
    steps: int = 10,
) -> Iterator[Callable[..., None]]:
    """Report the progress of a loop of ``total`` steps.

    On a terminal: a transient rich progress bar on stderr. Otherwise: a log line (INFO)
    every ``1/steps`` of the total and at the end, with the elapsed time.

    Example:
        >>> with progress(len(items), "render") as advance:  # doctest: +SKIP
        ...     for item in items:
        ...         advance(1, status="ok")

    Args:
        total: Number of steps (None: unknown; the log lines then come every 10 steps
            ... 10**k steps).
        description: What is being done (the bar's label, the log line's start).
        logger: Logger of the lines (default: ``scanguard.progress``).
        enabled: False: the callback does nothing.
        steps: Log lines per run when stderr is not a terminal.

    Yields:
        ``advance(n=1, status=None)``: ``n`` more steps are done; ``status`` is a short text
        shown with the bar or in the log line.
    """
    if not enabled:
        yield lambda n=1, status=None: None
        return
    log = logger or logging.getLogger("scanguard.progress")
    if stderr_is_terminal():
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

        with Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        ) as bar:
            task = bar.add_task(description, total=total)

            def on_bar(n: int = 1, status: str | None = None) -> None:
                text = description if status is None else f"{description}: {status}"
                bar.update(task, advance=n, description=text)

            yield on_bar
        return
    every = max(1, math.ceil(total / max(steps, 1))) if total else 1
    seen = 0
    next_at = every
    t0 = time.perf_counter()

    def on_log(n: int = 1, status: str | None = None) -> None:
        nonlocal seen, next_at, every
        seen += n
        if seen < next_at and not (total is not None and seen >= total):
            return
        while next_at <= seen:
            next_at += every
        if total is None and seen >= 10 * every:
            every *= 10
        done = f"{seen}/{total} ({round(100 * seen / max(total, 1))} %)" if total else str(seen)
        extra = "" if status is None else f", {status}"
        log.info("%s %s%s, %.0f s", description, done, extra, time.perf_counter() - t0)

    yield on_log
