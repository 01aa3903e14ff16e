"""The default run with its comparisons: instances one after the other, on threads, in workers.

`scanguard run` feeds every scan to the main (guarded) instance and to each comparison
(unguarded, classical gate). Three ways, each measured here in the same run:

* ``serial``: one after the other in the run's process (``instance_threads: 1``,
  ``instance_processes: off``; the baseline of the ratios);
* ``threads``: side by side on a thread pool (``instance_threads: 0``, processes off);
* ``processes``: the comparisons in a worker process (``instance_processes: on``; what
  ``auto``, the default, does for a long graph run, `scanguard.slam.detached`).

Every way must give the same trajectories bit for bit: the script checks it.

    python benchmarks/bench_instances.py [LOG ...] [--max-scans N] [--backend graph]
        [--modes serial threads processes]

Default logs: the three shared Freiburg benchmark logs (first 1500 scans each).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT.parent / "shared" / "data" / "benchmark"
LOGS = [BENCH / f"{name}.clf.gz" for name in ("intel", "fr079", "aces")]


#: mode -> (instance_threads, instance_processes)
MODES = {"serial": (1, "off"), "threads": (0, "off"), "processes": (1, "on")}


def _run(log: Path, mode: str, max_scans: int | None, backend: str) -> tuple[float, dict]:
    from scanguard.apps.run import run_recording
    from scanguard.apps.run_baseline import resolve_baseline
    from scanguard.detect.detector import FaultDetector
    from scanguard.io import read_sequence
    from scanguard.slam.config import RunConfig

    threads, processes = MODES[mode]
    cfg = RunConfig(
        backend=backend,
        instance_threads=threads,
        instance_processes=processes,
        max_scans=max_scans,
    )
    seq = read_sequence(str(log), max_scans=max_scans)
    detector = FaultDetector.load(None, backend="onnx", matcher=cfg.matcher)
    judge, info = resolve_baseline("auto", None, cfg.matcher)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = run_recording(
            seq, detector, Path(tmp), config=cfg, baseline=judge, baseline_info=info
        )
        wall = time.perf_counter() - t0
    return wall, res.trajectories


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path, default=LOGS)
    ap.add_argument("--max-scans", type=int, default=1500)
    ap.add_argument("--backend", default="graph")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    args = ap.parse_args()
    modes = ["serial"] + [m for m in args.modes if m != "serial"]
    print(f"cores: {os.cpu_count()}, load before: {os.getloadavg()[0]:.2f}")
    print(f"| log | scans | {' | '.join(f'{m} (s)' for m in modes)} | ratios | same trajectories |")
    print("|---|---|" + "---|" * len(modes) + "---|---|")
    for log in args.logs:
        # the first call also loads the kernels: warm them so no row pays for it
        _run(log, "serial", 50, args.backend)
        got = {m: _run(log, m, args.max_scans, args.backend) for m in modes}
        base, t1 = got["serial"]
        same = all(np.array_equal(t1[k], t[k], equal_nan=True) for _, t in got.values() for k in t1)
        walls = " | ".join(f"{w:.1f}" for w, _ in got.values())
        ratios = ", ".join(f"{m} {base / w:.2f}x" for m, (w, _) in got.items() if m != "serial")
        print(
            f"| {log.name} | {args.max_scans} | {walls} | {ratios} | {'yes' if same else 'NO'} |",
            flush=True,
        )
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
