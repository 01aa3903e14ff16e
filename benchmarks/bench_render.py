"""Scan-pair image rendering: scanguard.detect.render vs matplotlib (the paper's tool).

Run from the repository root: ``python benchmarks/bench_render.py [--repeats N]``.
All variants draw the same 1440-beam room pair into a 256x256 RGB image (red previous, blue
current, auto-fitted extent, no axes). Prints median milliseconds per image and the speed-up
against both matplotlib variants, measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.helpers import make_scan, room_segments

from scanguard.detect.render import (
    RenderStyle,
    render_extent,
    render_pair,
    render_pairs,
    save_png,
    to_rgb,
)
from scanguard.geometry import transform_points


def _median_ms(fn: Callable[[], object], repeats: int, per_call: int = 1) -> tuple[float, float]:
    """(best, median) wall-clock ms per image over ``repeats`` calls of ``fn``.

    The best (minimum) time is the timeit convention and the most repeatable figure on a
    shared, loaded machine: it is the run least disturbed by other processes. The median shows
    what a loaded machine really gives.
    """
    fn()  # warm-up
    wall = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        wall.append((time.perf_counter() - t) * 1e3 / per_call)
    return min(wall), statistics.median(wall)


def _loop(fn: Callable[[], object], n: int) -> Callable[[], None]:
    def run() -> None:
        for _ in range(n):
            fn()

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--examples", type=Path, help="also write an overview PNG of all styles here")
    args = ap.parse_args()

    seg = room_segments()
    rng = np.random.default_rng(0)
    prev = make_scan(seg, (0.0, 0.0, 0.0), noise=0.01, rng=rng).points()
    cur = make_scan(seg, (0.3, 0.1, 0.1), noise=0.01, rng=rng).points()
    pose = np.array([0.25, 0.1, 0.08])
    style = RenderStyle(overlap="current")
    x0, y0, side = render_extent(prev, cur, pose, style)
    moved = transform_points(pose, cur)

    def mpl_new() -> np.ndarray:
        fig = plt.figure(figsize=(2.56, 2.56), dpi=100)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        ax.set_xlim(x0, x0 + side)
        ax.set_ylim(y0, y0 + side)
        ax.plot(prev[:, 0], prev[:, 1], "o", color="r", ms=1.44, mew=0)
        ax.plot(moved[:, 0], moved[:, 1], "o", color="b", ms=1.44, mew=0)
        fig.canvas.draw()
        img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        plt.close(fig)
        return img

    fig = plt.figure(figsize=(2.56, 2.56), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    (lp,) = ax.plot([], [], "o", color="r", ms=1.44, mew=0)
    (lc,) = ax.plot([], [], "o", color="b", ms=1.44, mew=0)

    def mpl_reuse() -> np.ndarray:
        lp.set_data(prev[:, 0], prev[:, 1])
        lc.set_data(moved[:, 0], moved[:, 1])
        ax.set_xlim(x0, x0 + side)
        ax.set_ylim(y0, y0 + side)
        fig.canvas.draw()
        return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()

    fig2 = plt.figure(figsize=(2.56, 2.56), dpi=100)
    ax2 = fig2.add_axes((0, 0, 1, 1))
    ax2.set_axis_off()
    sp = ax2.scatter(prev[:, 0], prev[:, 1], s=1.0, c="r", linewidths=0)
    sc = ax2.scatter(moved[:, 0], moved[:, 1], s=1.0, c="b", linewidths=0)

    def mpl_scatter_reuse() -> np.ndarray:
        sp.set_offsets(prev)
        sc.set_offsets(moved)
        ax2.set_xlim(x0, x0 + side)
        ax2.set_ylim(y0, y0 + side)
        fig2.canvas.draw()
        return np.asarray(fig2.canvas.buffer_rgba())[..., :3].copy()

    b = args.batch
    prevs, curs, poses = [prev] * b, [cur] * b, np.tile(pose, (b, 1))
    rows: list[tuple[str, tuple[float, float]]] = [
        ("matplotlib plot(), new figure per image", _median_ms(mpl_new, max(5, args.repeats // 3))),
        ("matplotlib plot(), reused figure", _median_ms(mpl_reuse, args.repeats)),
        ("matplotlib scatter(), reused figure", _median_ms(mpl_scatter_reuse, args.repeats)),
    ]
    for name, st in [
        ("paper 256 RGB", RenderStyle()),
        ("occupancy 128 (2 ch)", RenderStyle.occupancy(128)),
        ("occupancy 64 (2 ch)", RenderStyle.occupancy(64)),
        ("metric 256 @ 5 cm (2 ch)", RenderStyle.metric(256)),
    ]:
        # Single calls are timed in blocks of `b` so that both rows measure equally long spans.
        single = _loop(lambda st=st: render_pair(prev, cur, pose, st), b)
        rows.append((f"scanguard {name}, single", _median_ms(single, args.repeats, b)))
        batch = _loop(lambda st=st: render_pairs(prevs, curs, poses, st), 1)
        rows.append((f"scanguard {name}, batch of {b}", _median_ms(batch, args.repeats, b)))
    plt.close(fig)
    plt.close(fig2)

    (new_best, _new_med), (reuse_best, reuse_med) = rows[0][1], rows[1][1]
    table = Table(title=f"Scan-pair rendering, {len(prev)}+{len(cur)} points, ms per image")
    table.add_column("variant")
    table.add_column("best ms", justify="right")
    table.add_column("median ms", justify="right")
    table.add_column("x vs mpl new fig (best)", justify="right")
    table.add_column("x vs mpl plot reused (best)", justify="right")
    table.add_column("x vs mpl plot reused (median)", justify="right")
    for name, (best, med) in rows:
        table.add_row(
            name,
            f"{best:.3f}",
            f"{med:.3f}",
            f"{new_best / best:.1f}",
            f"{reuse_best / best:.1f}",
            f"{reuse_med / med:.1f}",
        )
    Console().print(table)
    if args.examples:
        _write_examples(args.examples)


def _write_examples(path: Path) -> None:
    """One PNG: a correct and a faulty match (0.3 m, 5 deg off) in every style, side by side."""
    seg = room_segments()
    rng = np.random.default_rng(1)
    true = np.array([0.3, 0.1, 0.1])
    prev = make_scan(seg, (0.0, 0.0, 0.0), noise=0.01, rng=rng).points()
    cur = make_scan(seg, true, noise=0.01, rng=rng).points()
    faulty = true + np.array([0.3, 0.0, np.deg2rad(5.0)])
    tiles = []
    for st in (
        RenderStyle(),
        RenderStyle(overlap="current"),
        RenderStyle.occupancy(128),
        RenderStyle.metric(256, resolution=0.05),
    ):
        for pose in (true, faulty):
            img = to_rgb(render_pair(prev, cur, pose, st))
            k = 256 // img.shape[0]
            img = np.repeat(np.repeat(img, k, axis=0), k, axis=1)  # nearest-neighbour upscale
            tiles.append(np.pad(img, ((4, 4), (4, 4), (0, 0)), constant_values=128))
    top = np.concatenate(tiles[0::2], axis=1)
    bottom = np.concatenate(tiles[1::2], axis=1)
    save_png(path, np.concatenate([top, bottom], axis=0))
    print(f"wrote {path} (columns: paper mix, paper current-on-top, occupancy 128, metric 5 cm;")
    print(" top row: correct match, bottom row: 0.3 m / 5 deg off)")


if __name__ == "__main__":
    main()
