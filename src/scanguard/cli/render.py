"""Rich rendering of what the workflows return: report tables, a per-scan progress bar."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

from scanguard.apps.report import ReportTable
from scanguard.cli.main import console

logger = logging.getLogger("scanguard.cli")


def rich_table(report: ReportTable) -> Any:
    """``report`` as a rich table whose cells wrap (narrow terminals)."""
    from rich import box
    from rich.table import Table

    t = Table(
        title=report.title,
        title_justify="left",
        box=box.SIMPLE_HEAD,
        padding=(0, 0),
        show_edge=False,
    )
    for header, right in report.columns:
        t.add_column(header, justify="right" if right else "left", overflow="fold")
    for row in report.rows:
        if row is None:
            t.add_section()
        else:
            t.add_row(*row)
    if report.caption:
        t.caption = report.caption
    return t


def print_tables(tables: list[ReportTable], *, blank_before: bool = False) -> None:
    """Print ``tables``, each after a blank line when ``blank_before``, else between them."""
    for k, table in enumerate(tables):
        if blank_before or k > 0:
            console.print()
        console.print(rich_table(table))


@contextlib.contextmanager
def scan_progress(total: int) -> Iterator[Callable[[Any, int, int], None]]:
    """A per-scan callback: a progress bar on a terminal, else a log line every 10 %."""
    from scanguard.logging_utils import progress

    with progress(total, "scans", logger=logger) as advance:

        def on_step(d: Any, acc: int, rej: int) -> None:
            advance(1, status=f"guard accepted {acc} / rejected {rej}")

        yield on_step
