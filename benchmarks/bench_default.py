"""The default `scanguard run` against the same command at an earlier revision, same machine.

Speed work that must not change results is measured here: each log is run with the code of
``--baseline`` (a git revision, checked out into a temporary worktree and put first on
``PYTHONPATH``; the venv's packages are shared) and with the working tree, one after the
other, in fresh processes, and the script checks that the main trajectories are the same byte
for byte, and prints the main result's error of each side (mean relation error on the Freiburg
logs, ATE on a simulated recording) for changes allowed a stated tolerance. Nothing else
should run on the machine meanwhile.

    python benchmarks/bench_default.py --baseline f524083 [LOG ...] [--max-scans N]
        [--no-compare] [--repeats 1] [--cold]

Default logs: the three shared Freiburg benchmark logs. Both sides use the same user cache
(numba kernels are cached per source path, so the first baseline run compiles: a warm-up run
of each side on 20 scans comes first). ``--cold`` measures a user's first run instead: no
warm-up, and every run starts from an empty numba cache of its own (``NUMBA_CACHE_DIR``), so
it compiles every kernel it needs.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT.parent / "shared" / "data" / "benchmark"
LOGS = [BENCH / f"{name}.clf.gz" for name in ("intel", "fr079", "aces")]


def _run(
    src: Path | None, log: Path, out: Path, extra: list[str], cache: Path | None = None
) -> float:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    if cache is not None:  # an empty folder: a first run, every kernel compiled
        env["NUMBA_CACHE_DIR"] = str(cache)
    cmd = [str(Path(sys.executable).with_name("scanguard")), "run", str(log), "-o", str(out)]
    t0 = time.perf_counter()
    done = subprocess.run([*cmd, *extra], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{done.stderr[-1500:]}")
    return wall


def _error(out: Path) -> str:
    """The main result's mean translational relation error (all relations), or ATE, as text.

    The main result is the CNN-gated instance's (the default gate), else the only one.
    """
    metrics = json.loads((out / "metrics.json").read_text())
    rel = metrics.get("relations")
    table = rel["all"] if rel else metrics.get("errors", {})
    names = [k for k in table if k != "odometry"]
    if not names:
        return "-"
    main = next((k for k in names if k.endswith("+cnn")), names[0])  # the default gate's
    v = table[main]
    return f"{(v['trans_mean'] if rel else v.get('ate_rmse', float('nan'))):.4f}"


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path, default=LOGS)
    ap.add_argument("--baseline", required=True, help="git revision of the baseline")
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--no-compare", action="store_true")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--cold", action="store_true", help="each run from an empty numba cache")
    args = ap.parse_args()
    extra = ["--no-compare"] if args.no_compare else []
    if args.max_scans:
        extra += ["--max-scans", str(args.max_scans)]
    print(f"cores: {os.cpu_count()}, load before: {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "baseline"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(tree),
             args.baseline], check=True, capture_output=True,
        )  # fmt: skip
        try:
            rows = []
            for log in args.logs:
                for src in () if args.cold else (tree / "src", None):
                    # warm-up: compile and cache the kernels
                    _run(src, log, Path(tmp) / "warm", ["--no-compare", "--max-scans", "20"])
                walls: dict[str, list[float]] = {"baseline": [], "now": []}
                same = True
                for r in range(args.repeats):
                    outs = {}
                    for side, src in (("baseline", tree / "src"), ("now", None)):
                        outs[side] = Path(tmp) / f"{log.stem}-{side}-{r}"
                        cache = Path(tmp) / f"numba-{outs[side].name}" if args.cold else None
                        walls[side].append(_run(src, log, outs[side], extra, cache))
                    a, b = (outs[s] / "trajectory.tum" for s in ("baseline", "now"))
                    same = same and a.read_bytes() == b.read_bytes()
                    errs = f"{_error(outs['baseline'])} / {_error(outs['now'])}"
                base, now = statistics.median(walls["baseline"]), statistics.median(walls["now"])
                rows.append((log.name, base, now, same, errs))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                           capture_output=True)  # fmt: skip
    what = "run --no-compare" if args.no_compare else "run (with comparisons)"
    what += ", cold: every kernel compiled" if args.cold else ""
    print(
        f"| log ({what}) | baseline {args.baseline} (s) | now (s) | ratio | same trajectory "
        "| main error, baseline / now (m) |"
    )
    print("|---|---|---|---|---|---|")
    for name, base, now, same, errs in rows:
        print(
            f"| {name} | {base:.1f} | {now:.1f} | {base / now:.2f}x | {'yes' if same else 'NO'} "
            f"| {errs} |"
        )
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
