"""Reading speed of the CARMEN and ROS bag readers, against naive baselines in the same run.

Usage (repository root, venv active): ``python benchmarks/bench_io.py [--repeat 3]``.
Needs ../shared/data (the largest shared log, freiburg-079, and the largest bag).
"""

from __future__ import annotations

import argparse
import gzip
import time
from collections.abc import Callable
from pathlib import Path

from scanguard.io import read_sequence

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
LOG = SHARED / "carmen" / "freiburg-079-corrected.log.gz"
BAG = max((SHARED / "rosbag").glob("*.bag"), key=lambda p: p.stat().st_size)


def best(fn: Callable[[], int], repeat: int) -> tuple[float, int]:
    times, n = [], 0
    for _ in range(repeat):
        t = time.perf_counter()
        n = fn()
        times.append(time.perf_counter() - t)
    return min(times), n


def carmen_line_split() -> int:
    """Lower bound: gunzip and split into lines and tokens, no number parsing."""
    n = 0
    with gzip.open(LOG, "rt") as fh:
        for line in fh:
            if line.startswith("FLASER"):
                line.split()
                n += 1
    return n


def carmen_naive_floats() -> int:
    """Naive parser: one Python float() per token into lists."""
    scans = []
    with gzip.open(LOG, "rt") as fh:
        for line in fh:
            if line.startswith("FLASER"):
                tok = line.split()
                k = int(tok[1])
                scans.append([float(v) for v in tok[2 : k + 9]])
    return len(scans)


def carmen_reader() -> int:
    return len(read_sequence(LOG))


def bag_raw_deserialise() -> int:
    """Baseline: rosbags' AnyReader + deserialisation of every LaserScan, nothing else."""
    from rosbags.highlevel import AnyReader

    n = 0
    with AnyReader([BAG]) as reader:
        conns = [c for c in reader.connections if c.msgtype.endswith("LaserScan")]
        for c, _, raw in reader.messages(connections=conns):
            reader.deserialize(raw, c.msgtype)
            n += 1
    return n


def bag_reader() -> int:
    return len(read_sequence(BAG))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if not SHARED.exists():
        raise SystemExit(f"{SHARED} not found")
    import logging

    logging.disable(logging.WARNING)  # stamp warnings would repeat per run
    cases = [
        (LOG.name, "baseline: gunzip + line/token split", carmen_line_split, None),
        (LOG.name, "baseline: naive float() per token", carmen_naive_floats, None),
        (LOG.name, "read_sequence (CarmenReader)", carmen_reader, "carmen"),
        (BAG.name, "baseline: rosbags deserialise only", bag_raw_deserialise, None),
        (BAG.name, "read_sequence (RosbagReader)", bag_reader, "bag"),
    ]
    bag_reader()  # warm the typestore / imports so the first timed run is not penalised
    results: dict[str, tuple[float, int]] = {}
    for _file, what, fn, _ in cases:
        results[what] = best(fn, args.repeat)
    print(f"{'file':34} {'what':40} {'scans':>6} {'time s':>8} {'scans/s':>9} {'ratio':>8}")
    for file, what, _, kind in cases:
        t, n = results[what]
        if kind == "carmen":
            ratios = [
                f"{results['baseline: naive float() per token'][0] / t:.2f}x vs naive",
                f"{t / results['baseline: gunzip + line/token split'][0]:.2f}x of split",
            ]
        elif kind == "bag":
            ratios = [f"{t / results['baseline: rosbags deserialise only'][0]:.2f}x of raw"]
        else:
            ratios = ["1.00"]
        print(f"{file:34} {what:40} {n:6d} {t:8.3f} {n / t:9.0f}  {'; '.join(ratios)}")


if __name__ == "__main__":
    main()
