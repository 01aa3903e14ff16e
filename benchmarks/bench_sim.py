"""Simulator throughput: numba ray caster vs a numpy broadcast caster, and whole simulations.

Run: python benchmarks/bench_sim.py [--seconds 30]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.helpers import RPLIDAR, raycast

from scanguard.sim import cast_rays, load_scenario, simulate, simulate_run
from scanguard.sim.people import Crowd


def _circle_segments(circles: np.ndarray, n: int = 12) -> np.ndarray:
    """Circles as n-gons, so the numpy baseline (segments only) sees the same people."""
    a = np.linspace(0, 2 * np.pi, n + 1)
    out = []
    for x, y, r in circles:
        px, py = x + r * np.cos(a), y + r * np.sin(a)
        out.append(np.column_stack([px[:-1], py[:-1], px[1:], py[1:]]))
    return np.concatenate(out) if out else np.zeros((0, 4))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=30.0, help="simulated seconds per scenario")
    args = ap.parse_args()
    console = Console()

    # ray casting only: lobby world with 40 people, 1440 beams
    cfg = load_scenario("lobby")
    res = simulate_run(cfg, seed=0, duration=0.2)  # also compiles the kernels
    world = res.world
    crowd = Crowd.spawn(cfg.people, world, np.random.default_rng(0), world.start[:2], 0.3)
    circ, _ = crowd.shapes()
    ang = RPLIDAR.angle_min + RPLIDAR.angle_increment * np.arange(RPLIDAR.n_beams)
    segs = np.concatenate([world.segments, _circle_segments(np.concatenate([world.circles, circ]))])
    z = np.zeros(len(segs), np.int8)
    pose = np.array([world.start[0], world.start[1], 0.0])
    reps = 300
    t = time.perf_counter()
    for _ in range(reps):
        cast_rays(pose[:2], ang, segs, z, np.zeros((0, 3)), np.zeros(0, np.int8))
    numba_rate = reps / (time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(reps):
        cast_rays(pose[:2], ang, world.segments, world.segment_material,
                  np.concatenate([world.circles, circ]),
                  np.zeros(len(world.circles) + len(circ), np.int8))  # fmt: skip
    numba_circ_rate = reps / (time.perf_counter() - t)
    breps = 20
    t = time.perf_counter()
    for _ in range(breps):
        raycast(segs, pose)
    numpy_rate = breps / (time.perf_counter() - t)

    table = Table(title=f"ray casting, 1440 beams, {len(segs)} segments (40 people as 12-gons)")
    for col in ("caster", "scans/s", "ratio vs numpy"):
        table.add_column(col)
    table.add_row("numpy broadcast (tests.helpers.raycast)", f"{numpy_rate:.0f}", "1.0")
    table.add_row("numba, same segments", f"{numba_rate:.0f}", f"{numba_rate / numpy_rate:.1f}")
    table.add_row("numba, people as circles (as simulated)", f"{numba_circ_rate:.0f}",
                  f"{numba_circ_rate / numpy_rate:.1f}")  # fmt: skip
    console.print(table)

    table = Table(title=f"whole simulation ({args.seconds:.0f} s simulated, 10 Hz, 1440 beams)")
    for col in ("scenario", "agents", "scans", "wall s", "scans/s", "ratio vs numpy caster only"):
        table.add_column(col)
    for name in ("lobby", "corridor", "glass", "hall"):
        t = time.perf_counter()
        seq = simulate(name, seed=1, duration=args.seconds)
        dt = time.perf_counter() - t
        rate = len(seq) / dt
        table.add_row(name, str(seq.metadata["n_people"]), str(len(seq)), f"{dt:.1f}",
                      f"{rate:.0f}", f"{rate / numpy_rate:.1f}")  # fmt: skip
    console.print(table)


if __name__ == "__main__":
    main()
