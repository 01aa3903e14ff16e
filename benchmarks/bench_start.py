"""What a short run costs before and after its scans: start-up with and without PyTorch.

A run with the default onnxruntime back end needs the detector's exported network, not
PyTorch. Since session 14 the first load of a detector file remembers its metadata and export
(`scanguard.detect.onnx_export`), and later runs build the detector without importing PyTorch.
The baseline, measured in the same run: the same command with that entry missing (PyTorch
imported, the checkpoint read; the ONNX export itself cached, as before this change).

Each row is the median wall time of whole commands in fresh processes:
``scanguard run LOG --no-compare --max-scans N -o TMP`` (N small: the fixed cost of a run),
and the detector load alone (``FaultDetector.load(None, backend='onnx', matcher='plicp')``).

    python benchmarks/bench_start.py [--log LOG] [--max-scans 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT.parent / "shared" / "data" / "benchmark" / "intel.clf.gz"
LOAD = (
    "import sys; from scanguard.detect.detector import FaultDetector; "
    "FaultDetector.load(None, backend='onnx', matcher='plicp'); "
    "sys.exit(3 if 'torch' in sys.modules else 0)"
)


def _timed(cmd: list[str], env: dict[str, str]) -> tuple[float, int]:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    wall = time.perf_counter() - t0
    if done.returncode not in (0, 3):
        sys.exit(f"{' '.join(cmd)} failed: {done.stderr.decode()[-500:]}")
    return wall, done.returncode


def _forget_detectors(cache: Path) -> None:
    """The baseline: no remembered detector file (the ONNX exports stay)."""
    shutil.rmtree(cache / "scanguard" / "onnx-detector", ignore_errors=True)


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, default=LOG)
    ap.add_argument("--max-scans", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    scanguard = str(Path(sys.executable).with_name("scanguard"))
    print(f"cores: {os.cpu_count()}, load before: {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "cache"
        env = {**os.environ, "XDG_CACHE_HOME": str(cache)}
        out = Path(tmp) / "out"
        run = [scanguard, "run", str(args.log), "--no-compare", "--max-scans",
               str(args.max_scans), "-o", str(out)]  # fmt: skip
        load = [sys.executable, "-c", LOAD]
        _timed(run, env)  # fills the caches (ONNX export, numba's are per user already)
        rows = []
        for name, cmd in (("detector load", load), (f"run, {args.max_scans} scans", run)):
            base, new, torch_new = [], [], set()
            for _ in range(args.repeats):
                _forget_detectors(cache)
                base.append(_timed(cmd, env)[0])
                shutil.rmtree(out, ignore_errors=True)
                wall, rc = _timed(cmd, env)  # the entry the baseline run just wrote
                new.append(wall)
                torch_new.add(rc == 3)
                shutil.rmtree(out, ignore_errors=True)
            b, n = statistics.median(base), statistics.median(new)
            checked = "yes" if torch_new == {False} else "NO"
            rows.append((name, b, n, b / n, checked if cmd is load else "-"))
    print("| what | baseline: PyTorch imported (s) | from the cache (s) | ratio | no PyTorch |")
    print("|---|---|---|---|---|")
    for name, b, n, r, ok in rows:
        print(f"| {name} | {b:.2f} | {n:.2f} | {r:.2f}x | {ok} |")
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
