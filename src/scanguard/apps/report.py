"""Report tables of the workflows, as plain data: the command line prints them.

A `ReportTable` is a title, columns, rows of text and an optional caption; it does not know
how it is shown (the CLI renders it with rich, a notebook could render it as a data frame).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from scanguard.apps.run_result import gate_cells

#: The four counts of a build or store summary, in table order.
LABEL_COUNTS = ("pairs", "normal", "fault", "ambiguous")


@dataclasses.dataclass
class ReportTable:
    """A table of text cells.

    Attributes:
        title: Shown above the table.
        columns: ``(header, right-aligned)`` per column.
        rows: Cell texts per row; None is a section break (a rule between row groups).
        caption: Shown below the table ("" for none).
    """

    title: str
    columns: list[tuple[str, bool]]
    rows: list[list[str] | None] = dataclasses.field(default_factory=list)
    caption: str = ""

    def add_row(self, *cells: str) -> None:
        """Append a row of cell texts."""
        self.rows.append(list(cells))

    def add_section(self) -> None:
        """Start a new group of rows."""
        self.rows.append(None)


def fmt(v: Any, pct: bool = False) -> str:
    """A metric as table text: ``-`` for missing or not finite, 3 decimals or a percentage."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, float):
        return f"{100 * v:.1f}%" if pct else f"{v:.3f}"
    return str(v)


# --- run / demo: the guarded SLAM loop --------------------------------------------------------

#: One row per trajectory: the back end and its gate, the odometry and the matcher it used.
_SETUP = [("back end", False), ("gate", False), ("odometry", False), ("matcher", False)]


def _trajectory_errors(res: Any) -> ReportTable:
    t = ReportTable(
        "Trajectory errors against the reference (evo)",
        [*_SETUP, ("ATE m", True), ("RPE m", True), ("RPE °", True), ("Δ RPE", True)],
    )
    for name, e in res.errors.items():
        s = res.setup(name)
        red = 0.0 if name == res.unguarded else res.rpe_reduction(name)
        t.add_row(
            *(s[k] for k, _ in _SETUP),
            f"{e['ate_rmse']:.3f}",
            f"{e['rpe_trans_rmse']:.4f}",
            f"{e['rpe_rot_rmse_deg']:.2f}",
            f"{-100 * red:+.1f} %",
        )
    t.caption = (
        f"Δ RPE: RPE change against the unguarded {res.unguarded}; back end -: odometry alone"
    )
    return t


def _relations(res: Any) -> list[ReportTable]:
    tables = []
    for scope, table in res.relations.items():
        t = ReportTable(
            f"Relations ({scope}), Kümmerle et al. 2009",
            [*_SETUP, ("used", True), ("trans. m", True), ("rot. °", True)],
        )
        for name, r in table.items():
            s = res.setup(name)
            t.add_row(
                *(s[k] for k, _ in _SETUP),
                r.used_text(),
                f"{r.trans_mean:.3f} ± {r.trans_std:.3f}",
                f"{r.rot_mean_deg:.2f}",
            )
        t.caption = f"{res.relations_file}; mean ± std of the absolute errors (summary.md: all)"
        tables.append(t)
    if res.relations and res.published:
        t = ReportTable(
            "Published on this recording (Kümmerle et al. 2009, Table 1)",
            [("method", False), ("trans. m", True)],
        )
        for method, (mean, std) in res.published.items():
            t.add_row(method, f"{mean:.3f} ± {std:.3f}")
        tables.append(t)
    return tables


def _gates(res: Any) -> ReportTable:
    t = ReportTable(
        "Gates against reference labels (judged pairs, ambiguous excluded)",
        [
            *((k, False) for k in ("gate", "odometry", "matcher", "back end")),
            *((k, True) for k in ("pairs", "acc.", "prec.", "recall")),
        ],
    )
    for g in res.gates.values():
        t.add_row(*gate_cells(res, g))
    return t


def pipeline_tables(res: Any) -> list[ReportTable]:
    """The tables of a run's result (a `RunResult`): errors, relations, gates, latency."""
    tables = [_trajectory_errors(res)] if res.errors else []
    tables += _relations(res)
    if res.gates:
        tables.append(_gates(res))
    t = ReportTable(
        "Per-scan latency (ms)",
        [
            ("stage", False),
            ("matcher", False),
            ("back end", False),
            ("median", True),
            ("p95", True),
        ],
    )
    for k, (m, p) in res.latency_ms.items():
        t.add_row(k, res.matcher, res.backend, f"{m:.2f}", f"{p:.2f}")
    return [*tables, t]


# --- evaluate -----------------------------------------------------------------------------------

_SCORES = ("recall", "precision", "accuracy", "bal. acc.", "F1", "ECE", "AUC", "threshold")


def evaluation_tables(rows: Iterable[Mapping[str, Any]]) -> list[ReportTable]:
    """Counts and scores per method and environment (fault = positive) of `evaluate_store`."""
    head = [("method", False), ("environment", False)]
    counts = ReportTable(
        "fault detection (positive class: fault): counts",
        [*head, *((k, True) for k in ("TP", "FN", "FP", "TN")), ("ambiguous (flagged)", True)],
    )
    scores = ReportTable(
        "fault detection (positive class: fault): scores", [*head, *((k, True) for k in _SCORES)]
    )
    last = None
    for r in rows:
        if last is not None and r["method"] != last:
            counts.add_section()
            scores.add_section()
        last = r["method"]
        counts.add_row(
            r["method"],
            r["environment"],
            *(str(r[k]) for k in ("TP", "FN", "FP", "TN")),
            f"{r['n_ambiguous']} ({fmt(r['ambiguous_flagged'], pct=True)})",
        )
        scores.add_row(
            r["method"],
            r["environment"],
            *(fmt(r[k], pct=True) for k in ("recall", "precision", "accuracy")),
            fmt(r.get("balanced_accuracy")),
            fmt(r["f1"], pct=True),
            fmt(r.get("ece")),
            fmt(r["auc"]),
            fmt(r["threshold"]),
        )
    return [counts, scores]


# --- train, dataset build / stats -----------------------------------------------------------------


def training_table(preset: str, history: Sequence[Mapping[str, Any]], best: int) -> ReportTable:
    """The epochs of a training run; the best (kept) epoch is marked ``*``."""
    t = ReportTable(
        f"training {preset}",
        [(c, True) for c in ("epoch", "train loss", "train acc", "val loss", "val acc", "img/s")],
    )
    for h in history:
        mark = " *" if h["epoch"] == best else ""
        t.add_row(
            f"{h['epoch']}{mark}",
            f"{h['train_loss']:.4f}",
            f"{h['train_accuracy']:.4f}",
            f"{h['val_loss']:.4f}",
            f"{h['val_accuracy']:.4f}",
            f"{h['images_per_s']:.0f}",
        )
    return t


def build_table(title: str, summary: Any) -> ReportTable:
    """Pairs per sequence of a dataset build (a `BuildSummary`), and their total."""
    cols = ("sequence", "environment", "split", *LABEL_COUNTS)
    t = ReportTable(title, [(c, c in LABEL_COUNTS) for c in cols])
    for e in summary.entries:
        t.add_row(e["sequence"], e["environment"], e["split"], *(str(e[k]) for k in LABEL_COUNTS))
    tot = summary.totals()
    t.add_row("all", "", "", *(str(tot[k]) for k in LABEL_COUNTS))
    return t


def stats_table(title: str, rows: Iterable[Mapping[str, Any]]) -> ReportTable:
    """Pairs per environment of a store (rows of `write_stats`) with the fault rate."""
    cols = ("environment", "splits", "sequences", *LABEL_COUNTS)
    t = ReportTable(title, [(c, c not in ("environment", "splits")) for c in (*cols, "fault rate")])
    for r in rows:
        t.add_row(
            r["environment"],
            ",".join(r["splits"]),
            *(str(r[k]) for k in cols[2:]),
            f"{r['fault_rate']:.1%}",
        )
    return t
