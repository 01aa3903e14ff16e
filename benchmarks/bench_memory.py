"""Peak memory of ``scanguard run --backend frontend`` against the length of the recording.

Usage (repository root, venv active)::

    python benchmarks/bench_memory.py [--minutes 5 20] [--work DIR] [--src PATH]

For each length it simulates a recording (``scanguard simulate``, lobby, 10 Hz, kept in
``--work``), then measures in fresh processes the peak resident memory (ru_maxrss) of

* the reader alone (``read_sequence`` of the whole recording): the baseline of the run;
* ``scanguard run <recording> --backend frontend``;
* ``scanguard run <recording> --backend frontend --max-scans 200``.

It prints the peaks, the run's peak over the reader's, and the growth per scan between the
lengths (KB/scan: the slope of the run's peak). ``--src`` runs another checkout's code (e.g.
the previous behaviour: ``--src ../main/src``). No GPU is used.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from scanguard.fsutil import atomic_write_text

# runs a command and prints the peak RSS (KB) of its process tree's largest process
_PEAK = (
    "import resource, subprocess, sys\n"
    "rc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)"
    ".returncode\n"
    "print(rc, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
)
_CLI = "import sys; from scanguard.cli import app; sys.argv[0] = 'scanguard'; app()"
_READ = "import sys; from scanguard.io import read_sequence; print(len(read_sequence(sys.argv[1])))"


def peak_kb(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(peak RSS in KB, wall seconds) of ``cmd`` in a fresh process; exits on failure."""
    t = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", _PEAK, *cmd], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    if out[0] != "0":
        sys.exit(f"failed (exit {out[0]}): {' '.join(cmd)}")
    return float(out[1]), time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[5.0, 20.0])
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "bench_memory")
    ap.add_argument("--src", type=Path, default=None, help="run this checkout's src instead")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    env = dict(os.environ)
    if args.src is not None:
        env["PYTHONPATH"] = str(args.src.resolve())
    args.work.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    rows = []
    for minutes in args.minutes:
        bag = args.work / f"lobby-{minutes:g}min.mcap"
        if not bag.exists():
            sim = ["-c", _CLI, "simulate", "--duration", str(60 * minutes), "-o", str(bag)]
            subprocess.run([py, *sim], check=True, capture_output=True)
        n = int(
            subprocess.run(
                [py, "-c", _READ, str(bag)], env=env, capture_output=True, text=True, check=True
            ).stdout.split()[-1]
        )
        reader, _ = peak_kb([py, "-c", _READ, str(bag)], env)
        out = args.work / "out"
        run = [py, "-c", _CLI, "run", str(bag), "--backend", "frontend", "-o", str(out)]
        full, secs = peak_kb([*run, "--overwrite"], env)
        cut, _ = peak_kb([*run, "--overwrite", "--max-scans", "200"], env)
        rows.append(
            {
                "minutes": minutes,
                "scans": n,
                "reader_kb": reader,
                "run_kb": full,
                "run_max200_kb": cut,
                "run_s": secs,
            }
        )
        print(
            f"{minutes:g} min, {n} scans: reader {reader / 1024:.0f} MB, run {full / 1024:.0f} "
            f"MB ({full / reader:.2f}x the reader, {secs:.0f} s), run --max-scans 200 "
            f"{cut / 1024:.0f} MB",
            flush=True,
        )
    for a, b in itertools.pairwise(rows):
        slope = (b["run_kb"] - a["run_kb"]) / (b["scans"] - a["scans"])
        rslope = (b["reader_kb"] - a["reader_kb"]) / (b["scans"] - a["scans"])
        print(
            f"growth {a['minutes']:g} -> {b['minutes']:g} min: run {slope:.1f} KB/scan "
            f"(reader alone {rslope:.1f} KB/scan)"
        )
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
