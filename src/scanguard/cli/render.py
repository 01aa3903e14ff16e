"""Rich rendering of what the workflows return.

Report tables, a per-scan progress bar, and the exit status of a run whose relation figures
are partial.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

import typer

from scanguard.apps.report import ReportTable
from scanguard.cli.main import console, err_console

logger = logging.getLogger("scanguard.cli")

#: Exit status of a run whose result is written but whose relation figures are partial.
EXIT_PARTIAL_RELATIONS = 3


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


def exit_on_partial_relations(res: Any) -> None:
    """Exit with `EXIT_PARTIAL_RELATIONS` when a relation figure uses too few relations."""
    from scanguard.apps.run_headline import partial_relation_figures

    partial = partial_relation_figures(res)
    if partial:
        err_console.print(
            f"warning: relation figures on fewer than 95 % of the relations ({'; '.join(partial)})"
            f": marked PARTIAL in every table; exit status {EXIT_PARTIAL_RELATIONS}",
            highlight=False,
            soft_wrap=True,
        )
        raise typer.Exit(EXIT_PARTIAL_RELATIONS)
