"""Dataset benchmarks: labelling throughput and image rendering paths.

Usage: python benchmarks/bench_dataset.py [STORE] [--n 512]

1. Labelling: simulate + match + label + store one lobby sequence; pairs/s per stage.
2. Rendering ``n`` stored pairs at 64 px: ``render_all`` (batched) vs a ``PairDataset`` loop
   (one ``render_pair`` per item, as a DataLoader would do) — the ratio is the speed-up of
   pre-rendering for small images.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from scanguard.dataset import PairStore, label_sequence, write_sequence_file
from scanguard.detect.images import render_all
from scanguard.detect.render import RenderStyle
from scanguard.detect.torch_data import PairDataset
from scanguard.matching import get_matcher
from scanguard.pairs.labels import LabelConfig
from scanguard.sim import simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("store", nargs="?", default=None)
    ap.add_argument("--n", type=int, default=512)
    args = ap.parse_args()
    console = Console()
    rows = []

    t0 = time.perf_counter()
    seq = simulate("lobby", seed=7, duration=40.0, stride=2)
    t_sim = time.perf_counter() - t0
    n_pairs = len(seq) - 1
    timings = {}
    for gm in (False, True):
        t0 = time.perf_counter()
        rec = label_sequence(
            seq,
            environment="lobby",
            sequence="bench",
            split="train",
            matcher=get_matcher("icp-paper"),
            matcher_name="icp-paper",
            initial_guess="identity",
            labels=LabelConfig(),
            gmapping=gm,
        )
        timings[gm] = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_sequence_file(Path(tmp) / "bench.h5", rec)
        t_write = time.perf_counter() - t0
    base = timings[False] / n_pairs
    rows.append(("simulate (lobby, 5 Hz)", t_sim / n_pairs, t_sim / n_pairs / base))
    rows.append(("ICP (paper) + labels (baseline)", base, 1.0))
    rows.append(
        ("ICP + labels + gmapping score", timings[True] / n_pairs, timings[True] / n_pairs / base)
    )
    rows.append(("write HDF5", t_write / n_pairs, t_write / n_pairs / base))

    if args.store:
        store = PairStore.open(args.store)
    else:
        tmp = tempfile.mkdtemp()
        store = PairStore.open(write_sequence_file(Path(tmp) / "bench.h5", rec))
    idx = store.indices()[: args.n]
    style = RenderStyle.paper(size=64)
    ds = PairDataset(store, idx, style)
    ds.image(0)
    t0 = time.perf_counter()
    loop = np.stack([ds.image(k) for k in range(len(ds))])
    t_loop = (time.perf_counter() - t0) / len(idx)
    t0 = time.perf_counter()
    batch = render_all(store, idx, style)
    t_batch = (time.perf_counter() - t0) / len(idx)
    assert np.array_equal(loop, batch)
    rows.append(("render 64px: PairDataset loop (baseline)", t_loop, 1.0))
    rows.append(("render 64px: render_all", t_batch, t_batch / t_loop))

    table = Table(title=f"dataset benchmarks ({n_pairs} labelled pairs, {len(idx)} rendered)")
    table.add_column("stage")
    table.add_column("ms / pair", justify="right")
    table.add_column("ratio vs baseline", justify="right")
    for name, t, ratio in rows:
        table.add_row(name, f"{1000 * t:.2f}", f"{ratio:.2f}x")
    console.print(table)


if __name__ == "__main__":
    main()
