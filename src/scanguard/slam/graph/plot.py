"""The pose graph drawn over its map: nodes, edges, accepted and rejected loop closures."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.fsutil import save_figure


def save_graph_figure(
    panels: Mapping[str, tuple[Any, NDArray[np.float64], Sequence[Any], Sequence[Any]]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """One panel per graph: the map, the node poses, and the loop closures.

    Args:
        panels: Title -> ``(grid, node_poses, edges, closures)``: an `OccupancyGrid` (or
            None), node sensor poses ``(M, 3)``, `GraphBackend.edges`, and
            `GraphBackend.closures` (`ClosureRecord`).
        path: PNG path (written atomically).
        title: Figure title.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(panels))
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n, 6.5), squeeze=False)
    for ax, (name, (grid, nodes, edges, closures)) in zip(axes[0], panels.items(), strict=False):
        if grid is not None:
            ax.imshow(grid.to_image(), cmap="gray", vmin=0, vmax=255, extent=grid.extent)
        nodes = np.asarray(nodes, dtype=np.float64).reshape(-1, 3)
        if len(nodes):
            ax.plot(nodes[:, 0], nodes[:, 1], "-", color="tab:blue", lw=0.6, label="nodes")
            ax.plot(nodes[:, 0], nodes[:, 1], ".", color="tab:blue", ms=1.5)
            pad = 2.0
            ax.set_xlim(nodes[:, 0].min() - pad, nodes[:, 0].max() + pad)
            ax.set_ylim(nodes[:, 1].min() - pad, nodes[:, 1].max() + pad)
        n_acc = n_rej = n_drop = n_gate = 0
        for rec in closures:
            c = rec.candidate
            if not (0 <= c.node < len(nodes) and 0 <= c.target_node < len(nodes)):
                continue
            a, b = nodes[c.target_node], nodes[c.node]
            dropped = rec.dropped_final or rec.withdrawn
            if rec.added and not dropped:
                style, n_acc = ("-", "tab:green"), n_acc + 1
            elif dropped:
                style, n_drop = ("--", "tab:purple"), n_drop + 1
            elif rec.inconsistent:
                style, n_gate = ("-.", "tab:orange"), n_gate + 1
            else:
                style, n_rej = (":", "tab:red"), n_rej + 1
            ax.plot([a[0], b[0]], [a[1], b[1]], style[0], color=style[1], lw=0.9)
        ax.plot([], [], "-", color="tab:green", label=f"closures accepted ({n_acc})")
        ax.plot([], [], ":", color="tab:red", label=f"closures rejected ({n_rej})")
        if n_drop:
            ax.plot([], [], "--", color="tab:purple", label=f"withdrawn or dropped ({n_drop})")
        if n_gate:
            ax.plot([], [], "-.", color="tab:orange", label=f"refused by the gate ({n_gate})")
        ax.set_title(f"{name}: {len(nodes)} nodes, {len(edges)} edges")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        ax.legend(loc="upper right", fontsize=7)
    if title:
        fig.suptitle(title)
    return save_figure(fig, Path(path), dpi=110)
