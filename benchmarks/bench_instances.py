"""The default run with its comparisons: instances one after the other vs side by side.

`scanguard run` feeds every scan to the main (guarded) instance and to each comparison
(unguarded, classical gate). `RunConfig.instance_threads` 0 (the default) updates them on a
thread pool with the graph back end; 1 one after the other (the baseline of the ratio, measured
in the same run). Both runs must give the same trajectories bit for bit: the script checks it.

    python benchmarks/bench_instances.py [LOG ...] [--max-scans N] [--backend graph] [--threads T]

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


def _run(log: Path, threads: int, max_scans: int | None, backend: str) -> tuple[float, dict]:
    from scanguard.apps.run import run_recording
    from scanguard.apps.run_baseline import resolve_baseline
    from scanguard.detect.detector import FaultDetector
    from scanguard.io import read_sequence
    from scanguard.slam.config import RunConfig

    cfg = RunConfig(backend=backend, instance_threads=threads, max_scans=max_scans)
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
    ap.add_argument("--threads", type=int, default=0, help="instance_threads of the second run")
    args = ap.parse_args()
    print(f"cores: {os.cpu_count()}, load before: {os.getloadavg()[0]:.2f}")
    print(
        "| log | scans | one after the other (s) | side by side (s) | ratio | same trajectories |"
    )
    print("|---|---|---|---|---|---|")
    for log in args.logs:
        # the first call also loads the kernels: warm them so neither row pays for it
        _run(log, 1, 50, args.backend)
        base, t1 = _run(log, 1, args.max_scans, args.backend)
        par, t2 = _run(log, args.threads, args.max_scans, args.backend)
        same = all(np.array_equal(t1[k], t2[k], equal_nan=True) for k in t1)
        print(
            f"| {log.name} | {args.max_scans} | {base:.1f} | {par:.1f} | {base / par:.2f}x "
            f"| {'yes' if same else 'NO'} |",
            flush=True,
        )
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
