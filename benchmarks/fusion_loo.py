"""Leave-one-log-out choice of the fused motion design on the shared Freiburg logs.

Usage::

    python benchmarks/fusion_loo.py [--logs intel fr079 aces] [--max-scans N] [--out FILE]

Each candidate design (a `RunConfig` override, below) runs on each log with `scanguard run LOG
--no-compare` (raw wheel odometry, GMapping 30 particles seed 0, the shipped CNN); the figure is
the main result's mean absolute translational relation error over all relations. For each held
out log the rule picks the design with the smallest worst-case error on the other logs, and the
held-out log measures it; the design picked on all logs is the default. The baseline of the
ratio column is published GMapping (Kümmerle et al. 2009) on the same log. A run already in the
work folder is reused (the job resumes), so the script can be stopped and started again.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import yaml

from scanguard.fsutil import atomic_write_text

BENCH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "benchmark"
PUBLISHED_RBPF = {"intel": 0.070, "fr079": 0.061, "aces": 0.060}
#: The candidates measured on every log (README, "The default: one fused motion model").
DESIGNS: dict[str, dict[str, object]] = {
    "fused icp-paper sigma 0.02 (default)": {},
    "fused plicp sigma 0.005": {
        "matcher": "plicp",
        "allow_other_matcher": True,
        "fusion": {"match_sigma": 0.005},
    },
    "fused icp-paper sigma 0.01 hold 10": {
        "fusion": {"match_sigma": 0.01, "wheel_flag_hold": 10},
    },
}


def run_one(log: str, name: str, override: dict[str, object], work: Path, max_scans: int | None
            ) -> float:  # fmt: skip
    """The main result's relation error of one design on one log (reused when already run)."""
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
    out = work / f"{log}-{slug}" if max_scans is None else work / f"{log}-{slug}-{max_scans}"
    metrics = out / "metrics.json"
    if not metrics.exists():
        cfg = work / f"{out.name}.yaml"
        atomic_write_text(cfg, yaml.safe_dump(override or {"backend": "gmapping"}))
        cmd = ["scanguard", "run", str(BENCH / f"{log}.clf.gz"), "--no-compare", "-o", str(out),
               "--config", str(cfg), "--overwrite"]  # fmt: skip
        if max_scans:
            cmd += ["--max-scans", str(max_scans)]
        print(f"running {name} on {log} ...", file=sys.stderr, flush=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    m = json.loads(metrics.read_text())
    return float(m["relations"]["all"]["gmapping+cnn"]["trans_mean"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=["intel", "fr079", "aces"])
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--work", type=Path, default=Path("runs/fusion_loo"))
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    err = {
        (name, log): run_one(log, name, o, args.work, args.max_scans)
        for name, o in DESIGNS.items()
        for log in args.logs
    }
    lines = ["| design | " + " | ".join(args.logs) + " |", "|---" * (len(args.logs) + 1) + "|"]
    for name in DESIGNS:
        cells = [f"{err[name, g]:.3f} (x{err[name, g] / PUBLISHED_RBPF[g]:.2f})" for g in args.logs]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "| held out | chosen on the others | held-out error (m) |", "|---|---|---|"]
    for held in args.logs:
        train = [g for g in args.logs if g != held]
        pick = min(DESIGNS, key=lambda n: max(err[n, g] for g in train))
        lines.append(f"| {held} | {pick} | {err[pick, held]:.3f} |")
    pick = min(DESIGNS, key=lambda n: max(err[n, g] for g in args.logs))
    lines += ["", f"chosen on all logs (the default): {pick}"]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        atomic_write_text(args.out, text)


if __name__ == "__main__":
    main()
