"""Dataset statistics: per-environment label counts and error histograms (PNG)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from scanguard.dataset.store import PairStore
from scanguard.fsutil import atomic_write_text, save_figure
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL, LabelConfig

log = logging.getLogger(__name__)


def label_counts(store: PairStore) -> list[dict[str, Any]]:
    """Rows per environment plus a total row: pairs, normal, fault, ambiguous, fault rate.

    The fault rate is over the labelled (non-ambiguous) pairs, like the paper's 36 %.
    """
    rows = store.summary()
    total = {
        "environment": "all",
        "splits": sorted(set(store.records["split"].tolist())),
        "sequences": len(set(store.records["sequence"].tolist())),
        "pairs": sum(r["pairs"] for r in rows),
        "normal": sum(r["normal"] for r in rows),
        "fault": sum(r["fault"] for r in rows),
        "ambiguous": sum(r["ambiguous"] for r in rows),
    }
    out = [*rows, total]
    for r in out:
        lab = r["normal"] + r["fault"]
        r["fault_rate"] = r["fault"] / lab if lab else float("nan")
    return out


def _log_bins(values: np.ndarray, lo: float, hi: float, n: int = 60) -> np.ndarray:
    v = values[np.isfinite(values) & (values > 0)]
    vmin = max(lo, float(v.min())) if v.size else lo
    vmax = min(hi, float(v.max())) if v.size else hi
    vmax = max(vmax, vmin * 10)
    return np.logspace(math.log10(vmin), math.log10(vmax), n)


def error_histograms(
    store: PairStore, out_dir: str | Path, labels: LabelConfig | None = None
) -> list[Path]:
    """One PNG per environment: histograms of the three errors with the thresholds marked.

    Bars are stacked by label (normal, ambiguous, fault); errors are on log axes because
    they span from millimetres (good matches) to metres (failures).

    Args:
        store: The pair store.
        out_dir: Destination directory (``hist_<environment>.png``).
        labels: Thresholds to draw (default: those the first file was built with).

    Returns:
        The PNG paths.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = labels or store.label_config(0)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    r = store.records
    panels = [
        (
            "disp_error",
            1.0,
            "mean point displacement (m)",
            cfg.normal_displacement,
            cfg.fault_displacement,
            (1e-4, 50.0),
        ),
        (
            "trans_error",
            1.0,
            "translation error (m)",
            cfg.normal_translation,
            cfg.fault_translation,
            (1e-4, 50.0),
        ),
        (
            "rot_error",
            180.0 / math.pi,
            "rotation error (deg)",
            cfg.normal_rotation_deg,
            cfg.fault_rotation_deg,
            (1e-3, 180.0),
        ),
    ]
    paths = []
    for env in store.environments:
        m = r["environment"] == env
        fig = _environment_figure(plt, r, m, panels)
        lab = r["label"][m]
        n_lab = int((lab != AMBIGUOUS).sum())
        rate = float((lab == FAULT).sum()) / n_lab if n_lab else float("nan")
        fig.suptitle(
            f"{env}: {int(m.sum())} pairs, fault rate {rate:.0%} of labelled "
            "(dashed: normal limit, solid: fault limit)"
        )
        dest = save_figure(fig, out / f"hist_{env}.png", dpi=90)
        paths.append(dest)
    return paths


_COLOURS = {NORMAL: "tab:blue", AMBIGUOUS: "tab:gray", FAULT: "tab:red"}
_NAMES = {NORMAL: "normal", AMBIGUOUS: "ambiguous", FAULT: "fault"}


def _environment_figure(
    plt: Any, r: dict[str, np.ndarray], m: np.ndarray, panels: list[tuple[Any, ...]]
) -> Any:
    """The three stacked histograms of one environment's pairs (``m``: its rows)."""
    lab = r["label"][m]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, (col, scale, title, lo_t, hi_t, rng) in zip(axes, panels, strict=True):
        vals = np.asarray(r[col][m], dtype=np.float64) * scale
        # clip into the plotted range so exact zeros and huge failures stay visible
        vals = np.clip(np.nan_to_num(vals, nan=rng[1], posinf=rng[1]), rng[0], rng[1])
        bins = _log_bins(vals, *rng)
        data = [vals[lab == k] for k in (NORMAL, AMBIGUOUS, FAULT)]
        ax.hist(
            data,
            bins=bins,
            stacked=True,
            color=[_COLOURS[k] for k in (NORMAL, AMBIGUOUS, FAULT)],
            label=[
                f"{_NAMES[k]} ({d.size})"
                for k, d in zip((NORMAL, AMBIGUOUS, FAULT), data, strict=True)
            ],
        )
        ax.set_xscale("log")
        ax.axvline(lo_t, color="k", ls="--", lw=1)
        ax.axvline(hi_t, color="k", ls="-", lw=1)
        ax.set_xlabel(title)
        ax.set_ylabel("pairs")
    axes[0].legend(fontsize=8, loc="upper left")
    return fig


def write_stats(store: PairStore, out_dir: str | Path) -> tuple[list[dict[str, Any]], Path]:
    """Counts as JSON (``stats.json``) plus the histograms; returns the rows and JSON path."""
    rows = label_counts(store)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    error_histograms(store, out)
    dest = out / "stats.json"
    atomic_write_text(dest, json.dumps(rows, indent=1) + "\n")
    return rows, dest
