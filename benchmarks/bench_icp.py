"""ICP speed: our numba ICP vs a straightforward numpy + cKDTree ICP vs small_gicp.

Workload: 1440-beam scans (RPLidar A3 geometry) in the synthetic room of tests/helpers, 1 cm
range noise, motions drawn like 10 Hz driving (|t| <= 5 cm, |theta| <= 3 deg), identity
initial guess; every method runs on the same pair back to back (interleaved, so machine load
hits all alike). Rows with 2 threads (ours `ICPConfig(threads=2)`, cKDTree `workers=2`) are
the same-parallelism comparison; CPU time is the process's (all threads, incl. spinning
workers), so a parallel row shows what it costs the machine, not only its wall-clock.
A second table checks agreement with small_gicp on 200 real consecutive pairs of the CCNY
bag (skipped when /work/shared/data is absent).

Run: python benchmarks/bench_icp.py [--pairs 200]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np
from rich.console import Console
from rich.table import Table
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.helpers import make_scan, room_segments  # noqa: E402

from scanguard.geometry import compose  # noqa: E402
from scanguard.matching import ICPConfig, as_points, icp_point_to_line, icp_point_to_point  # noqa: E402
from scanguard.matching.reference import icp_point_to_point_reference  # noqa: E402

DATA = ROOT.parent / "shared" / "data"

try:
    import small_gicp
except ImportError:  # the peer is optional
    small_gicp = None


def small_gicp_icp(src: np.ndarray, tgt: np.ndarray, cfg: ICPConfig) -> tuple[np.ndarray, int]:
    """small_gicp point-to-point ICP on z = 0 points, exact NN, our stop rule."""
    s3 = np.hstack([src, np.zeros((len(src), 1))])
    t3 = np.hstack([tgt, np.zeros((len(tgt), 1))])
    tc = small_gicp.PointCloud(t3)
    sc = small_gicp.PointCloud(s3)
    tree = small_gicp.KdTree(tc)
    r = small_gicp.align(
        tc,
        sc,
        tree,
        registration_type="ICP",
        max_correspondence_distance=1e3,
        num_threads=1,
        max_iterations=cfg.max_iterations,
        rotation_epsilon=math.radians(cfg.rotation_tol_deg),
        translation_epsilon=cfg.translation_tol,
    )
    T = r.T_target_source
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])]), int(r.iterations)


def make_pairs(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    seg = room_segments()
    pairs = []
    for _ in range(n):
        start = np.array([rng.uniform(-2, 2), rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi)])
        ang = rng.uniform(0, 2 * np.pi)
        step = np.array(
            [
                0.05 * math.sqrt(rng.uniform()) * math.cos(ang),
                0.05 * math.sqrt(rng.uniform()) * math.sin(ang),
                math.radians(rng.uniform(-3, 3)),
            ]
        )
        tgt = as_points(make_scan(seg, start, noise=0.01, rng=rng))
        src = as_points(make_scan(seg, compose(start, step), noise=0.01, rng=rng))
        pairs.append((src, tgt, step))
    return pairs


CPU_MS: list[float] = []  # process CPU time (all threads) of the last `timed` call


def timed(fn, *args, **kw):
    c0 = time.process_time()
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    CPU_MS[:] = [(time.process_time() - c0) * 1e3]
    return out, (time.perf_counter() - t0) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument(
        "--plot", type=Path, default=None, help="write a PNG of the time distributions here"
    )
    args = ap.parse_args()
    console = Console(width=220)
    cfg = ICPConfig()
    cfg2 = ICPConfig(threads=2)
    paper = ICPConfig.paper()
    pairs = make_pairs(args.pairs)
    # warm up the JIT (cache=True: compiled code is loaded from disk after the first run)
    t0 = time.perf_counter()
    icp_point_to_point(pairs[0][0], pairs[0][1])
    icp_point_to_line(pairs[0][0], pairs[0][1])
    icp_point_to_point(pairs[0][0], pairs[0][1], None, cfg2)
    console.print(f"first call (JIT load/compile): {time.perf_counter() - t0:.2f} s")
    console.print(
        f"numba threading layer: {numba.threading_layer()}, {numba.get_num_threads()} threads"
    )

    names = [
        "ours icp (default)",
        "ours icp-paper",
        "ours plicp",
        "numpy+cKDTree (default)",
        "ours icp (default, threads=2)",
        "numpy+cKDTree (default, workers=2)",
    ]
    if small_gicp is not None:
        names.append("small_gicp ICP (default)")
    # the baseline of each row at the same parallelism
    same_par = {n: names[5] if "2)" in n else names[3] for n in names}
    ms: dict[str, list[float]] = {k: [] for k in names}
    iters: dict[str, list[int]] = {k: [] for k in names}
    err_t: dict[str, list[float]] = {k: [] for k in names}
    err_r: dict[str, list[float]] = {k: [] for k in names}

    cpu: dict[str, list[float]] = {k: [] for k in names}

    def record(name, pose, it, t, truth):
        ms[name].append(t)
        cpu[name].append(CPU_MS[0])
        iters[name].append(it)
        err_t[name].append(float(np.hypot(*(pose[:2] - truth[:2]))))
        err_r[name].append(abs(math.degrees(pose[2] - truth[2])))

    for src, tgt, step in tqdm(pairs, desc="pairs"):
        r, t = timed(icp_point_to_point, src, tgt, None, cfg)
        record(names[0], r.pose, r.iterations, t, step)
        r, t = timed(icp_point_to_point, src, tgt, None, paper)
        record(names[1], r.pose, r.iterations, t, step)
        r, t = timed(icp_point_to_line, src, tgt, None, cfg)
        record(names[2], r.pose, r.iterations, t, step)
        (pose, it, _c), t = timed(icp_point_to_point_reference, src, tgt, None, cfg)
        record(names[3], pose, it, t, step)
        r, t = timed(icp_point_to_point, src, tgt, None, cfg2)
        record(names[4], r.pose, r.iterations, t, step)
        (pose, it, _c), t = timed(icp_point_to_point_reference, src, tgt, None, cfg, workers=2)
        record(names[5], pose, it, t, step)
        if small_gicp is not None:
            (pose, it), t = timed(small_gicp_icp, src, tgt, cfg)
            record(names[6], pose, it, t, step)

    ref_med = float(np.median(ms[names[3]]))
    sg_med = float(np.median(ms[names[6]])) if small_gicp is not None else float("nan")
    table = Table(
        title=f"ICP on {len(pairs)} synthetic 1440-point pairs (wall-clock, loaded machine)"
    )
    for col in (
        "method",
        "median ms",
        "p95 ms",
        "median CPU ms",
        "median iters",
        "median err mm",
        "median err deg",
        "x faster than cKDTree",
        "x vs cKDTree same threads (wall / CPU)",
        "x faster than small_gicp",
    ):
        table.add_column(col, justify="right" if col != "method" else "left")
    for n in names:
        med = float(np.median(ms[n]))
        table.add_row(
            n,
            f"{med:.2f}",
            f"{np.percentile(ms[n], 95):.2f}",
            f"{np.median(cpu[n]):.2f}",
            f"{np.median(iters[n]):.0f}",
            f"{np.median(err_t[n]) * 1e3:.2f}",
            f"{np.median(err_r[n]):.3f}",
            f"{ref_med / med:.1f}",
            f"{float(np.median(ms[same_par[n]])) / med:.1f} / "
            f"{float(np.median(cpu[same_par[n]])) / float(np.median(cpu[n])):.1f}",
            f"{sg_med / med:.2f}",
        )
    console.print(table)
    cpu_ratio = float(np.median(cpu[names[3]])) / float(np.median(cpu[names[0]]))
    console.print(
        f"CPU-time ratio cKDTree / ours (default): {cpu_ratio:.1f}x; load {os.getloadavg()}"
    )
    par = np.array(ms[names[4]]) / np.array(ms[names[0]])
    console.print(
        f"threads=2 / threads=1 wall-clock per pair: median {np.median(par):.2f}, "
        f"p95 {np.percentile(par, 95):.2f}; share of pairs where 2 threads are faster: "
        f"{(par < 1).mean():.0%}"
    )
    if args.plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 4))
        ax.boxplot([ms[n] for n in names], vert=False, showfliers=False)
        ax.set_yticks(range(1, len(names) + 1), names)
        ax.set_xscale("log")
        ax.set_xlabel("ms per match (1440-point pairs, log scale)")
        ax.set_title("ICP speed, same pairs back to back")
        fig.tight_layout()
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.plot, dpi=120)
        console.print(f"plot: {args.plot}")

    bag = DATA / "rosbag" / "ccny_laser_scan_matcher_demo.bag"
    if small_gicp is None or not bag.exists():
        console.print("real-data agreement check skipped (no small_gicp or no shared data)")
        return
    from scanguard.io import read_sequence

    seq = read_sequence(bag)
    dts, dths, ours_ms, sg_ms = [], [], [], []
    for i in tqdm(range(min(200, len(seq) - 1)), desc="ccny pairs"):
        tgt = as_points(seq[i])
        src = as_points(seq[i + 1])
        r, t1 = timed(icp_point_to_point, src, tgt, None, cfg)
        (pose, _it), t2 = timed(small_gicp_icp, src, tgt, cfg)
        ours_ms.append(t1)
        sg_ms.append(t2)
        d = r.pose - pose
        dts.append(math.hypot(d[0], d[1]))
        dths.append(abs(math.degrees(d[2])))
    t2 = Table(title=f"Agreement with small_gicp ICP on {len(dts)} real CCNY pairs (681 beams)")
    for col in (
        "median |dt| mm",
        "p95 |dt| mm",
        "median |dtheta| deg",
        "ours median ms",
        "small_gicp median ms",
        "ratio",
    ):
        t2.add_column(col, justify="right")
    t2.add_row(
        f"{np.median(dts) * 1e3:.4f}",
        f"{np.percentile(dts, 95) * 1e3:.3f}",
        f"{np.median(dths):.5f}",
        f"{np.median(ours_ms):.2f}",
        f"{np.median(sg_ms):.2f}",
        f"{np.median(sg_ms) / np.median(ours_ms):.2f}",
    )
    console.print(t2)


if __name__ == "__main__":
    main()
