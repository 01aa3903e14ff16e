"""Scale-out benchmarks (issue 13): sharded dataset builds and torchrun training.

Usage: python benchmarks/bench_scale.py [--sequences 6] [--duration 96] [--epochs 4]
       [--repeats 2] [--skip-ray] [--skip-train] [--store DIR] [--out DIR]

1. Dataset build of a small version of ``configs/paper.yaml`` (every environment, its matcher,
   labels and GMapping score; ``--sequences`` per environment of ``--duration`` s, the office
   1) with: 1 worker in this process (baseline), a local process pool of 2, Ray with 1 and 2
   workers, taking turns for ``--repeats`` rounds (best time counted). Every build must give
   the first in-process build's store exactly (every record column: labels, matched poses).
   Targets: Ray 2 workers >= 1.7x Ray 1 worker; Ray <= 10 % slower than the local pool at 2
   workers. ``ray.init`` (starting the local "cluster") is timed apart: on a real cluster it
   is already running.
2. Training (``configs/train.yaml``'s hybrid model, ``--epochs``, patience off) on the store
   from step 1, once with ``torchrun --nproc-per-node 1`` and once with 2 (gloo, same global
   batch, the config's 2 threads shared by the processes). Target: the 2-process run's best
   validation accuracy within 1 point of the 1-process run; throughput in images/s (training
   epochs only, rendering excluded). A third run (1 process, the seed + 1) shows how far two
   runs that differ only in their random draws land apart.

The 1-min load average before and after each part is printed: the machine has 2 cores that
other jobs share, so every speed-up here is bounded by what the others leave.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from scanguard.dataset import DatasetConfig, PairStore, build_dataset
from scanguard.runtime.executor import LocalExecutor, make_executor

ROOT = Path(__file__).resolve().parents[1]
console = Console(width=120)


def load() -> str:
    """The 1-min load average."""
    return f"{os.getloadavg()[0]:.2f}"


def bench_config(sequences: int, duration: float) -> DatasetConfig:
    """``configs/paper.yaml`` with fewer, shorter sequences (as tests/test_pinned_build.py)."""
    data = DatasetConfig.from_yaml(ROOT / "configs" / "paper.yaml").model_dump(mode="json")
    for env in data["environments"]:
        env["sequences"] = 1 if env.get("heldout") else sequences
        env["duration"] = duration
    data["name"] = "bench-scale"
    data["splits"] = {"val_sequences": 1, "test_sequences": 0, "seed": 0}
    return DatasetConfig.from_dict(data)


def same_store(a: Path, b: Path) -> bool:
    """Every record column equal (labels and matched poses included)."""
    ra, rb = PairStore.open(a).records, PairStore.open(b).records
    return ra.keys() == rb.keys() and all(np.array_equal(ra[k], rb[k]) for k in ra)


def timed_build(cfg: DatasetConfig, out: Path, executor: Any) -> float:
    t0 = time.perf_counter()
    s = build_dataset(cfg, out, progress=False, executor=executor)
    dt = time.perf_counter() - t0
    if s.failed or not s.complete:
        raise SystemExit(f"{out}: build failed: {s.failed}")
    return dt


def bench_dataset(args: argparse.Namespace, work: Path) -> Path:
    cfg = bench_config(args.sequences, args.duration)
    n_seq = sum(e.sequences for e in cfg.environments)
    console.print(f"dataset: {n_seq} sequences x {args.duration:g} s, load {load()}")
    runs: list[tuple[str, Any]] = [("local, 1 worker (in-process)", None)]
    runs.append(("local pool, 2 workers", LocalExecutor(2)))
    ray: Any = None
    if not args.skip_ray:
        try:
            import ray
        except ImportError:
            console.print("ray not installed: pip install 'scanguard[scale]' (Ray rows skipped)")
        else:
            runs += [("ray, 1 worker", 1), ("ray, 2 workers", 2)]
    times: dict[str, list[float]] = {name: [] for name, _ in runs}
    loads: dict[str, list[str]] = {name: [] for name, _ in runs}
    same: dict[str, bool] = {}
    base_dir = work / "run0-0"  # the in-process build of the first round: the reference
    init_s: list[float] = []
    # the executors take turns, ``--repeats`` rounds: other jobs' load hits all of them
    for rep in range(args.repeats):
        for k, (name, how) in enumerate(runs):
            out = work / f"run{k}-{rep}"
            executor = how
            if isinstance(how, int):
                t0 = time.perf_counter()
                ray.init(num_cpus=how, include_dashboard=False, log_to_driver=False)
                init_s.append(time.perf_counter() - t0)
                executor = make_executor("ray", workers=how)
            try:
                times[name].append(timed_build(cfg, out, executor))
            finally:
                if isinstance(how, int):
                    ray.shutdown()
            loads[name].append(load())
            if out != base_dir:
                same[name] = same.get(name, True) and same_store(base_dir, out)
                shutil.rmtree(out, ignore_errors=True)
    pairs = len(PairStore.open(base_dir))
    best = {name: min(t) for name, t in times.items()}
    base = best[runs[0][0]]
    table = Table(title=f"dataset build: {n_seq} sequences, {pairs} pairs, best of {args.repeats}")
    for col in ("executor", "seconds (runs)", "x in-process", "identical", "load after each"):
        table.add_column(col, justify="left" if col == "executor" else "right")
    for name, _ in runs:
        table.add_row(
            name,
            f"{best[name]:.1f} ({', '.join(f'{t:.1f}' for t in times[name])})",
            f"{base / best[name]:.2f}",
            str(same[name]) if name in same else "reference",
            ", ".join(loads[name]),
        )
    console.print(table)
    local2 = best["local pool, 2 workers"]
    console.print(f"local pool 2 vs in-process: {base / local2:.2f}x")
    if "ray, 2 workers" in best:
        r1, r2 = best["ray, 1 worker"], best["ray, 2 workers"]
        console.print(
            f"ray 2 vs ray 1 worker: {r1 / r2:.2f}x (target >= 1.7); ray vs local pool at 2 "
            f"workers: {100 * (r2 / local2 - 1):+.1f} % (target <= +10 %); ray.init "
            f"{min(init_s):.1f}-{max(init_s):.1f} s, not counted (a cluster is already up)"
        )
    return base_dir


def bench_train(args: argparse.Namespace, store: Path, work: Path) -> None:
    import yaml

    cfg = yaml.safe_load((ROOT / "configs" / "train.yaml").read_text())
    cfg.update(epochs=args.epochs, patience=0)
    torchrun = Path(sys.executable).with_name("torchrun")
    results: dict[str, dict[str, Any]] = {}
    # the third run is the noise floor: one process, another seed
    for label, n, seed in (("1", 1, cfg["seed"]), ("2", 2, cfg["seed"]), ("1, seed+1", 1, None)):
        run_cfg = dict(cfg, seed=cfg["seed"] + 1) if seed is None else cfg
        cfg_path = work / f"train-{n}-{run_cfg['seed']}.yaml"
        cfg_path.write_text(yaml.safe_dump(run_cfg))
        out = work / f"train{n}-{run_cfg['seed']}"
        cmd = [
            str(torchrun),
            "--standalone",
            f"--nproc-per-node={n}",
            "--no-python",
            sys.executable,
            "-c",
            "from scanguard.cli import app; app()",
            "train",
            "-d",
            str(store),
            "-c",
            str(cfg_path),
            "-o",
            str(out),
        ]
        before = load()
        t0 = time.perf_counter()
        env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        hist = json.loads((out / "history.json").read_text())
        best = max(hist, key=lambda h: (h["val_accuracy"], -h["val_loss"]))
        results[label] = {
            "wall": wall,
            "ips": float(np.median([h["images_per_s"] for h in hist])),
            "best_val": best["val_accuracy"],
            "loss": [round(h["train_loss"], 4) for h in hist],
            "load": f"{before} -> {load()}",
        }
    table = Table(title=f"torchrun training ({cfg['preset']}, {args.epochs} epochs, batch 16)")
    for col in ("processes", "img/s (median epoch)", "x 1 process", "best val acc", "wall s"):
        table.add_column(col, justify="right")
    table.add_column("load before -> after")
    for label, r in results.items():
        table.add_row(
            label,
            f"{r['ips']:.0f}",
            f"{r['ips'] / results['1']['ips']:.2f}",
            f"{100 * r['best_val']:.2f} %",
            f"{r['wall']:.0f}",
            r["load"],
        )
    console.print(table)
    gap = 100 * abs(results["2"]["best_val"] - results["1"]["best_val"])
    noise = 100 * abs(results["1, seed+1"]["best_val"] - results["1"]["best_val"])
    console.print(
        f"accuracy gap 2 vs 1 process: {gap:.2f} points (target <= 1); "
        f"1 process, seed vs seed+1: {noise:.2f} points"
    )
    for label, r in results.items():
        console.print(f"train loss per epoch, {label} process(es): {r['loss']}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sequences", type=int, default=6)
    ap.add_argument("--duration", type=float, default=96.0)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=2, help="Rounds of the dataset builds.")
    ap.add_argument("--skip-ray", action="store_true")
    ap.add_argument("--skip-train", action="store_true")
    ap.add_argument("--store", default=None, help="Train on this store (no dataset builds).")
    ap.add_argument("--out", default=None, help="Keep the builds here (default: a temp dir).")
    args = ap.parse_args()
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_scale_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        store = Path(args.store) if args.store else bench_dataset(args, work)
        if not args.skip_train:
            bench_train(args, store, work)
    finally:
        if not args.out:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
