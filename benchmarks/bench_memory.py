"""Peak memory of ``scanguard run`` against the length of the recording.

Usage (repository root, venv active)::

    python benchmarks/bench_memory.py [--logs fr079 aces] [--lengths 1000 2000 4000 0]
        [--modes default no-compare mcap] [--pingpong 3] [--work DIR] [--src PATH]

For each log (``../shared/data/benchmark/<name>.clf.gz``, or a path), each mode and each
length it measures in a fresh process the peak resident memory (over its process tree) of
``scanguard run LOG [--max-scans N]`` with the mode's options:

* ``default``: the default run with its comparison instances;
* ``no-compare``: the main (guarded) instance alone;
* ``mcap``: the default run that also writes ``result.mcap``.

A length of 0 is the whole log. ``--pingpong K`` adds a longer recording made from the whole
log: K passes, every other one backwards in time with increasing stamps (the odometry stays
continuous at each turn and the map area is the log's own, so what grows is what the length
costs). It prints each peak, its ratio against the shortest length of the same mode and log
(the baseline, measured in the same run), and the growth per scan between lengths (KB/scan).
``--src`` runs another checkout's code (e.g. ``--src ../main/src``). No GPU is used.
"""

from __future__ import annotations

import argparse
import gzip
import itertools
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from scanguard.fsutil import atomic_write_bytes, atomic_write_text

logger = logging.getLogger("bench_memory")

# runs a command and prints its peak memory (KB): the larger of its largest process's peak
# (ru_maxrss) and the sum of the RSS of its process tree sampled every 0.1 s (a run's worker
# processes, `scanguard.slam.detached`, hold memory at the same time as the run)
_PEAK = (
    "import os, resource, subprocess, sys, time\n"
    "def tree(pid):\n"
    "    total, todo = 0, [pid]\n"
    "    while todo:\n"
    "        p = todo.pop()\n"
    "        try:\n"
    "            pages = int(open(f'/proc/{p}/statm').read().split()[1])\n"
    "            total += pages * os.sysconf('SC_PAGESIZE')\n"
    "            todo += [int(c) for c in open(f'/proc/{p}/task/{p}/children').read().split()]\n"
    "        except OSError:\n"
    "            pass\n"
    "    return total // 1024\n"
    "proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
    "peak = 0\n"
    "while proc.poll() is None:\n"
    "    peak = max(peak, tree(proc.pid))\n"
    "    time.sleep(0.1)\n"
    "print(proc.returncode, max(peak, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))\n"
)
_CLI = "import sys; from scanguard.cli import app; sys.argv[0] = 'scanguard'; app()"
MODES: dict[str, list[str]] = {
    "default": [],
    "no-compare": ["--no-compare"],
    "mcap": ["--mcap"],
}
DATA = Path("../shared/data/benchmark")


def peak_kb(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(peak RSS in KB, wall seconds) of ``cmd`` in a fresh process; exits on failure."""
    t = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", _PEAK, *cmd], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    if out[0] != "0":
        sys.exit(f"failed (exit {out[0]}): {' '.join(cmd)}")
    return float(out[1]), time.perf_counter() - t


def _stamp_of(line: str) -> float:
    return float(line.split()[-3])


def _restamped(line: str, stamp: float) -> str:
    tok = line.split()
    tok[-3] = tok[-1] = f"{stamp:.6f}"
    return " ".join(tok)


def pingpong_log(src: Path, passes: int, work: Path) -> Path:
    """A CARMEN log of ``passes`` passes over ``src``, every other one backwards in time.

    Stamps keep increasing (a pass starts one mean period after the previous one ended);
    the comment lines are kept once, at the top.
    """
    dest = work / f"{src.name.split('.')[0]}-pingpong{passes}.clf.gz"
    if dest.exists():
        return dest
    with gzip.open(src, "rt") as f:
        lines = f.read().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    body = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    t0, t1 = _stamp_of(body[0]), _stamp_of(body[-1])
    gap = (t1 - t0) / max(1, len(body) - 1)
    out, base = list(head), t0
    for p in range(passes):
        seq = body if p % 2 == 0 else body[::-1]
        for ln in seq:
            t = _stamp_of(ln)
            out.append(_restamped(ln, base + (t - t0 if p % 2 == 0 else t1 - t)))
        base += (t1 - t0) + gap
    atomic_write_bytes(dest, gzip.compress(("\n".join(out) + "\n").encode()))
    return dest


def measure(log: Path, mode: str, length: int, work: Path, env: dict[str, str]) -> dict[str, Any]:
    """One configuration: peak RSS and wall time of ``scanguard run``."""
    out = work / "out"
    cmd = [sys.executable, "-c", _CLI, "run", str(log), "-o", str(out), "--overwrite"]
    cmd += MODES[mode] + (["--max-scans", str(length)] if length else [])
    kb, secs = peak_kb(cmd, env)
    return {"log": log.name, "mode": mode, "max_scans": length, "peak_kb": kb, "seconds": secs}


def _scans(log: Path, env: dict[str, str]) -> int:
    code = "import sys; from scanguard.io import read_sequence as r; print(len(r(sys.argv[1])))"
    res = subprocess.run(
        [sys.executable, "-c", code, str(log)], env=env, capture_output=True, text=True, check=True
    )
    return int(res.stdout.split()[-1])


def report(rows: list[dict[str, Any]]) -> None:
    """Each peak against the shortest length of its log and mode; the growth per scan."""
    key = lambda r: (r["log"], r["mode"])  # noqa: E731
    for (log, mode), grp in itertools.groupby(sorted(rows, key=key), key=key):
        g = sorted(grp, key=lambda r: r["scans"])
        base = g[0]
        for r in g:
            logger.info(
                "%s %-10s %6d scans: peak %5.0f MB (x%.2f the %d-scan baseline), %.0f s",
                log, mode, r["scans"], r["peak_kb"] / 1024, r["peak_kb"] / base["peak_kb"],
                base["scans"], r["seconds"],
            )  # fmt: skip
        for a, b in itertools.pairwise(g):
            slope = (b["peak_kb"] - a["peak_kb"]) / max(1, b["scans"] - a["scans"])
            logger.info(
                "%s %-10s growth %d -> %d scans: %.1f KB/scan",
                log, mode, a["scans"], b["scans"], slope,
            )  # fmt: skip


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--logs", nargs="+", default=["fr079", "aces"])
    ap.add_argument("--lengths", type=int, nargs="+", default=[1000, 2000, 4000, 0])
    ap.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES))
    ap.add_argument("--pingpong", type=int, default=0, help="also K passes of the whole log")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "bench_memory")
    ap.add_argument("--src", type=Path, default=None, help="run this checkout's src instead")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    env = dict(os.environ)
    if args.src is not None:
        env["PYTHONPATH"] = str(args.src.resolve())
    args.work.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    for name in args.logs:
        log = Path(name) if Path(name).exists() else DATA / f"{name}.clf.gz"
        n = _scans(log, env)
        runs = [(log, k, min(k, n) if k else n) for k in args.lengths if k < n]
        if args.pingpong > 1:
            long = pingpong_log(log, args.pingpong, args.work)
            runs.append((long, 0, _scans(long, env)))
        for (path, k, scans), mode in itertools.product(runs, args.modes):
            row = {**measure(path, mode, k, args.work, env), "log": name, "scans": scans}
            logger.info("%s", json.dumps(row))
            rows.append(row)
    report(rows)
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
