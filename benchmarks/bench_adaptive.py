"""The adaptive operating point's cost per judged pair: the sorted window against numpy's.

`AdaptiveOperatingPoint.observe` keeps its window (200 logits) sorted by bisection and reads
the quantile and the lower-side median from it (`sorted_mode_and_spread`); the baseline,
measured in the same run, is what it did before: numpy's quantile and medians on the window
copied into an array. The script checks that both give the same thresholds, bit for bit.

    python benchmarks/bench_adaptive.py [--n 20000] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from collections import deque

import numpy as np

from scanguard.detect.adaptive import AdaptiveOperatingPoint, logit, mode_and_spread


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    p = 1.0 / (1.0 + np.exp(-rng.normal(0.0, 1.0, args.n)))
    op = AdaptiveOperatingPoint(0.25)
    cfg = op.config
    t0 = time.perf_counter()
    fast = []
    for v in p:
        op.observe(float(v))
        fast.append((op.mode, op.spread))
    new = (time.perf_counter() - t0) / args.n
    window: deque[float] = deque(maxlen=cfg.window)
    t0 = time.perf_counter()
    slow = []
    for k, v in enumerate(p):
        window.append(logit(float(v)))
        u = np.fromiter(window, dtype=np.float64, count=len(window))
        slow.append(mode_and_spread(u, cfg) if k + 1 >= cfg.warmup else (np.nan, np.nan))
    old = (time.perf_counter() - t0) / args.n
    same = all(
        (a == c or (np.isnan(a) and np.isnan(c))) and (b == d or (np.isnan(b) and np.isnan(d)))
        for (a, b), (c, d) in zip(fast, slow, strict=True)
    )
    print("| observe, window 200 | numpy window (baseline) | sorted window | ratio | same |")
    print("|---|---|---|---|---|")
    print(f"| us per pair | {old * 1e6:.1f} | {new * 1e6:.1f} | {old / new:.1f}x | {same} |")


if __name__ == "__main__":
    main()
