"""How much a graph result owes to its loop-search schedule: the default run at every phase.

The graph searches for loops at every ``loop_search_every``-th node; which nodes that is (the
phase, `GraphConfig.loop_search_phase`) is arbitrary, and a user's recording falls on any of
them. Each log is run at every phase with otherwise default settings, and the script prints
the main result's error at each (mean relation error on the Freiburg logs, ATE on a
simulated recording), its ratio against phase 0 (the default) and whether it folded: an error
above ``--fold-ratio`` times the log's smallest. With ``--compare`` the unguarded comparison
is run too, so that "the guard never costs" can be checked at every phase.

    python benchmarks/bench_fragility.py [LOG ...] [--work runs/fragility] [--compare]
        [--graph KEY=VALUE ...] [--json OUT.json]

``--graph KEY=VALUE`` sets a `GraphConfig` field in every run (a setting measured against
the default: run once without, once with, and compare the tables).

Default logs: the three shared Freiburg benchmark logs. Runs whose ``metrics.json`` already
exists under ``--work`` are read, not rerun (the job resumes). No speed target: the figures
are accuracy, recorded in README ("A building at hospital scale, and how fragile the
graph's closures are") and benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from scanguard.fsutil import atomic_write_text  # noqa: E402

BENCH = ROOT.parent / "shared" / "data" / "benchmark"
LOGS = [BENCH / f"{name}.clf.gz" for name in ("intel", "fr079", "aces")]
EVERY = 3  # GraphConfig.loop_search_every's default


def _errors(out: Path) -> dict[str, float]:
    """Per instance: the mean translational relation error (all relations), else the ATE."""
    metrics = json.loads((out / "metrics.json").read_text())
    rel = metrics.get("relations")
    table = rel["all"] if rel else metrics.get("errors", {})
    key = "trans_mean" if rel else "ate_rmse"
    return {k: float(v[key]) for k, v in table.items() if k != "odometry"}


def _run(
    log: Path, phase: int, work: Path, compare: bool, graph: list[str]
) -> tuple[dict[str, float], float]:
    """The errors of one run (read back when it was done before) and its wall time."""
    tag = "".join(f"_{g.replace('=', '')}" for g in graph)
    out = work / f"{log.name.split('.')[0]}_phase{phase}{'_cmp' if compare else ''}{tag}"
    if (out / "metrics.json").is_file():
        return _errors(out), float("nan")
    work.mkdir(parents=True, exist_ok=True)
    cfg = work / f"phase{phase}{tag}.yaml"
    lines = [f"  loop_search_phase: {phase}"] + [f"  {g.replace('=', ': ', 1)}" for g in graph]
    atomic_write_text(cfg, "graph:\n" + "\n".join(lines) + "\n")
    cmd = [str(Path(sys.executable).with_name("scanguard")), "run", str(log), "-o", str(out)]
    cmd += ["--config", str(cfg), "--overwrite"] + ([] if compare else ["--no-compare"])
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
    if done.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{done.stderr[-1500:]}")
    return _errors(out), time.perf_counter() - t0


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path, default=LOGS)
    ap.add_argument("--work", type=Path, default=Path("runs/fragility"))
    ap.add_argument("--compare", action="store_true", help="also the unguarded comparison")
    ap.add_argument("--fold-ratio", type=float, default=1.5)
    ap.add_argument("--graph", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    print(f"cores: {os.cpu_count()}, load before: {os.getloadavg()[0]:.2f}; graph: {args.graph}")
    print("| log | phase | main error | ratio to phase 0 | folded | unguarded | wall (s) |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for log in args.logs:
        runs = [(p, *_run(log, p, args.work, args.compare, args.graph)) for p in range(EVERY)]
        mains = [next(v for k, v in e.items() if k.endswith("+cnn")) for _, e, _ in runs]
        least = min(mains)
        for (phase, errs, wall), main in zip(runs, mains, strict=True):
            unguarded = errs.get("graph", float("nan")) if args.compare else float("nan")
            row = {"log": log.name, "phase": phase, "main": main, "unguarded": unguarded,
                   "ratio": main / mains[0], "folded": main > args.fold_ratio * least,
                   "wall_s": wall}  # fmt: skip
            rows.append(row)
            print(f"| {log.name} | {phase} | {main:.4f} | {row['ratio']:.2f} | "
                  f"{'yes' if row['folded'] else 'no'} | {unguarded:.4f} | {wall:.0f} |",
                  flush=True)  # fmt: skip
    print(f"load after: {os.getloadavg()[0]:.2f}")
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
