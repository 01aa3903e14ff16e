"""Preview PNG of a simulation: the world by material, the robot path and the people's tracks."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from scanguard.errors import ConfigError
from scanguard.fsutil import save_figure
from scanguard.geometry import compose, transform_points
from scanguard.sim.engine import SimulationResult
from scanguard.sim.people import CART
from scanguard.sim.world import GLASS, MIRROR

log = logging.getLogger(__name__)

_COLOURS = {0: "#222222", GLASS: "#2aa7d6", MIRROR: "#c83cc8"}


def save_preview(
    result: SimulationResult, path: str | Path, *, scan_index: int | None = None, dpi: int = 90
) -> Path:
    """Draw the world, robot path, people's tracks and one scan; write a PNG atomically.

    Args:
        result: A `simulate_run` result.
        path: Destination PNG.
        scan_index: Scan to overlay (world frame, ground-truth pose); default the middle one
            (the only one a run that streamed its scans, ``keep_scans=False``, keeps).
        dpi: Resolution.

    Returns:
        The written path.

    Raises:
        ConfigError: ``scan_index`` is out of range, or names a scan the run did not keep.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    world, seq = result.world, result.sequence
    res_ref = result.robot_path[:: result.config.stride]
    xmin, ymin, xmax, ymax = world.bounds
    aspect = (ymax - ymin) / max(xmax - xmin, 1e-6)
    width = 8.0
    fig, ax = plt.subplots(figsize=(width, float(np.clip(width * aspect, 2.5, 9.0)) + 0.6))
    tracks = result.people_tracks
    for k in range(tracks.shape[1]):
        colour = "#e08a2c" if result.people_kinds[k] == CART else "#9fc79a"
        ax.plot(tracks[:, k, 0], tracks[:, k, 1], color=colour, lw=0.6, alpha=0.7)
    if tracks.shape[1]:
        ax.scatter(tracks[-1, :, 0], tracks[-1, :, 1], s=6, color="#3f8a3a", zorder=3,
                   label="people (last position)")  # fmt: skip
    n = len(seq) if len(seq) else result.n_kept
    i = n // 2 if scan_index is None else scan_index
    if not 0 <= i < n:
        raise ConfigError(f"preview: scan_index {i} is out of range (0..{n - 1})")
    if len(seq):
        scan = seq[i]
    elif i == n // 2 and result.middle_scan is not None:
        scan = result.middle_scan
    else:
        raise ConfigError(f"preview: scan {i} was streamed, not kept (only scan {n // 2} is)")
    laser = compose(res_ref[i], seq.laser_offset)
    pts = transform_points(laser, scan.points(np.float64))
    ax.scatter(pts[:, 0], pts[:, 1], s=0.4, color="#d62728", zorder=4, label=f"scan {i}")
    for code, colour in _COLOURS.items():
        m = world.segment_material == code
        if m.any():
            lines = world.segments[m].reshape(-1, 2, 2)
            ax.add_collection(LineCollection(list(lines), colors=colour, linewidths=1.6 if code
                                             else 1.0, zorder=5))  # fmt: skip
        for x, y, r in world.circles[world.circle_material == code]:
            ax.add_patch(plt.Circle((x, y), r, color=colour, fill=False, lw=1.0, zorder=5))
    ax.plot(result.robot_path[:, 0], result.robot_path[:, 1], color="#1f5fbf", lw=1.4, zorder=6,
            label="robot (ground truth)")  # fmt: skip
    ax.plot(*result.robot_path[0, :2], "o", color="#1f5fbf", ms=5, zorder=7)
    ax.plot([], [], color=_COLOURS[GLASS], label="glass")
    ax.plot([], [], color=_COLOURS[MIRROR], label="mirror")
    ax.set_xlim(xmin - 1, xmax + 1)
    ax.set_ylim(ymin - 1, ymax + 1)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    meta = seq.metadata
    ax.set_title(
        f"{meta['scenario']} (seed {meta['seed']}): {n} scans, {meta['n_people']} agents, "
        f"{scan.n_beams} beams",
        fontsize=10,
    )
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8, markerscale=4)
    dest = save_figure(fig, Path(path), dpi=dpi)
    log.info("preview written to %s", dest)
    return dest
