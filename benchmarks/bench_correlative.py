"""Correlative matcher speed: branch-and-bound vs brute force at the finest level.

Workload: a 360-beam scan (12 m range, noise-free) of the synthetic room of tests/helpers
against a local map of 10 scans taken along a short path (3600 points). Rows:

- ``local``: window +-0.3 m, +-0.35 rad around an initial pose 0.17/-0.11 m, 0.08 rad off;
- ``loop``: window +-4 m, +-pi around an initial pose (2.5, -3, 2.0) off (a loop search).

Each row times branch-and-bound (median of ``--repeats`` calls, after a warm-up that compiles)
and the exhaustive search of the same lattice (``--brute-repeats`` calls; skipped when it would
score more than ``--brute-max`` poses), checks they find the same best score, and prints the
ratio. Also times the grid build and ``match_to_map`` (search + ICP refinement).

Run: python benchmarks/bench_correlative.py [--repeats 20]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.helpers import raycast, room_segments  # noqa: E402

from scanguard.geometry import transform_points  # noqa: E402
from scanguard.matching import _correlative as _k  # noqa: E402
from scanguard.matching.config import CorrelativeConfig  # noqa: E402
from scanguard.matching.correlative import (  # noqa: E402
    _theta_offsets,
    correlative_match,
    match_to_map,
    theta_step_for,
)
from scanguard.matching.likelihood import LikelihoodGrid  # noqa: E402
from scanguard.scan import SensorInfo  # noqa: E402

SENSOR = SensorInfo(
    name="360-beam",
    n_beams=360,
    angle_min=-math.pi,
    angle_increment=2 * math.pi / 360,
    range_min=0.1,
    range_max=12.0,
    rate_hz=10.0,
)
TRUE = np.array([0.4, -0.3, 0.15])


def scan_points(segments: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Sensor-frame points of a 360-beam scan at ``pose``."""
    r = raycast(segments, pose, SENSOR).astype(np.float64)
    a = SENSOR.angle_min + SENSOR.angle_increment * np.arange(SENSOR.n_beams)
    ok = np.isfinite(r)
    return np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])


def brute(
    grid: LikelihoodGrid, src: np.ndarray, init: np.ndarray, wxy: float, wth: float
) -> tuple[float, np.ndarray, int]:
    """Exhaustive finest-level search of the lattice `correlative_match` searches."""
    r = grid.resolution
    offsets, _step = _theta_offsets(wth, theta_step_for(src, r))
    ix, iy = _k.discretise(src, init[0], init[1], init[2], offsets, *grid.origin, r)
    w = math.ceil(wxy / r - 1e-9)
    k, dx, dy, best, n = _k.brute_force(grid.stack, grid.pad, ix, iy, w)
    pose = np.array([init[0] + dx * r, init[1] + dy * r, init[2] + offsets[k]])
    return best / len(src), pose, n


def lattice_size(src: np.ndarray, r: float, wxy: float, wth: float) -> int:
    """Number of finest-level poses in the window."""
    offsets, _ = _theta_offsets(wth, theta_step_for(src, r))
    w = math.ceil(wxy / r - 1e-9)
    return len(offsets) * (2 * w + 1) ** 2


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--brute-repeats", type=int, default=1)
    ap.add_argument("--brute-max", type=float, default=3e7, help="max poses for brute force")
    args = ap.parse_args()

    segs = room_segments()
    path = [np.array([0.12 * i, 0.05 * i - 0.2, 0.03 * i]) for i in range(10)]
    local = np.vstack([transform_points(p, scan_points(segs, p)) for p in path])
    src = scan_points(segs, TRUE)
    cases = [
        ("local", 0.02, 4, 0.3, 0.35, np.array([0.17, -0.11, 0.08])),
        ("local", 0.05, 4, 0.3, 0.35, np.array([0.17, -0.11, 0.08])),
        ("loop", 0.05, 7, 4.0, math.pi, np.array([2.5, -3.0, 2.0])),
        ("loop", 0.02, 8, 4.0, math.pi, np.array([2.5, -3.0, 2.0])),
    ]
    table = Table(title=f"correlative matcher, {len(src)}-point scan vs {len(local)}-point map")
    for col in (
        "case", "res (m)", "levels", "window", "build (ms)", "B&B (ms)", "poses scored",
        "brute (ms)", "poses", "ratio", "same score", "pose err (cm, mrad)", "match_to_map (ms)",
    ):  # fmt: skip
        table.add_column(col, justify="right")
    for name, r, levels, wxy, wth, off in cases:
        cfg = CorrelativeConfig(resolution=r, levels=levels, window_xy=wxy, window_theta=wth)
        t = time.perf_counter()
        grid = LikelihoodGrid.from_points(local, cfg)
        build = time.perf_counter() - t
        init = TRUE - off
        correlative_match(src, grid, init, cfg)  # warm-up (compiles on a cold cache)
        times = []
        for _ in range(args.repeats):
            res = correlative_match(src, grid, init, cfg)
            times.append(res.time_s)
        bb = statistics.median(times)
        match_to_map(src, grid, init, cfg)
        mt = statistics.median(
            [match_to_map(src, grid, init, cfg)[0].time_s for _ in range(args.repeats)]
        )
        n_all = lattice_size(src, r, wxy, wth)
        if n_all <= args.brute_max:
            bt = []
            for _ in range(args.brute_repeats):
                t = time.perf_counter()
                b_score, _b_pose, _n = brute(grid, src, init, wxy, wth)
                bt.append(time.perf_counter() - t)
            b_time = statistics.median(bt)
            brute_ms = f"{b_time * 1e3:.1f}"
            ratio = f"{b_time / bb:.0f}x"
            same = "yes" if abs(b_score - res.score) < 1e-9 else f"NO ({b_score:.4f})"
        else:
            brute_ms, ratio, same = "skipped", "-", "-"
        err = res.pose - TRUE
        table.add_row(
            name, f"{r}", str(levels), f"+-{wxy} m, +-{wth:.2f}", f"{build * 1e3:.1f}",
            f"{bb * 1e3:.2f}", f"{res.n_evaluated}", brute_ms, f"{n_all:.2e}", ratio, same,
            f"{np.hypot(err[0], err[1]) * 100:.1f}, {abs(err[2]) * 1e3:.1f}", f"{mt * 1e3:.2f}",
        )  # fmt: skip
    Console(width=220).print(table)


if __name__ == "__main__":
    main()
