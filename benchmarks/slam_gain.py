"""SLAM gain table: RPE of plain ICP vs ICP gated by the CNN, by a baseline, and by the oracle.

Runs `scanguard.apps.run.run_recording` on the simulated Environments 1-5 and on the shared
real recordings, then prints one markdown table (also written to ``<out>/slam_gain.md``): per
sequence the RPE (translation RMSE per scan pair, evo) of plain ICP, CNN-gated ICP,
baseline-gated ICP and oracle-gated ICP, the reductions against plain ICP next to the paper's
75 % (its Fig. 19), and the paper's own metric (mean centroid distance of the matched scans).

Odometry used on rejected steps: the simulated environments are run twice, with the
simulator's wheel odometry (``recorded``) and with odometry simulated from the ground truth by
`scanguard.pairs.odometry.OdometryNoise` (``simulated``: 1 cm + 5 % per axis and step, 0.5 deg
+ 5 % of the turn + 1 deg/m), the noise the real corrected logs always get (their recorded
odometry is not aligned with the corrected scans). The baseline is `resolve_baseline("auto")`.

ICP initial guess: identity on the simulated environments (the paper's setting, and how the
training data was matched); the odometry increment on the real recordings (``--real-initial-
guess``), as `scanguard.dataset.build_from_recording` matched them (their scans are far apart:
the corrected Intel, ACES and CSAIL logs keep one scan every 0.7-1 m and 10-20 deg).

    python benchmarks/slam_gain.py [--model PATH] [--duration 30] [--out /tmp/slam_gain]
                                   [--only lobby,intel] [--max-scans 3000]

Needs a trained model (default: the shipped one).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from scanguard.apps.run import run_recording
from scanguard.apps.run_baseline import resolve_baseline
from scanguard.detect.detector import FaultDetector
from scanguard.io import read_sequence
from scanguard.sim import simulate
from scanguard.slam.config import RunConfig
from scanguard.slam.guard import GuardConfig

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SIMULATED = {
    "Env 1 lobby (sim)": "lobby",
    "Env 2 corridor (sim)": "corridor",
    "Env 3 glass (sim)": "glass",
    "Env 4 hall (sim)": "hall",
    "Env 5 office (sim)": "office",
}
REAL: dict[str, tuple[str, dict[str, Any]]] = {
    "Intel lab (CARMEN)": ("carmen/intel-corrected.log.gz", {}),
    "ACES (CARMEN)": ("carmen/aces-corrected.log.gz", {}),
    "CSAIL (CARMEN)": ("carmen/csail-corrected.log.gz", {}),
    "FR079 (CARMEN)": ("carmen/freiburg-079-corrected.log.gz", {}),
    "leg_tracker (static, ROS bag)": (
        "rosbag/leg_tracker_positive_1.bag",
        {"scan_topic": "right_scan", "reference": "static"},
    ),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default=None)
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--out", default="/tmp/slam_gain")
    ap.add_argument("--max-scans", type=int, default=3000, help="per real recording")
    ap.add_argument("--only", default="", help="comma list of substrings of the row labels")
    ap.add_argument(
        "--real-initial-guess",
        choices=("odometry", "identity"),
        default="odometry",
        help="ICP initial guess on the real recordings (the real-data dataset used odometry)",
    )
    args = ap.parse_args()
    det = FaultDetector.load(args.model, backend="onnx")
    judge, judge_info = resolve_baseline("auto")
    print(f"baseline: {judge_info}", flush=True)
    out = Path(args.out)
    jobs: list[tuple[str, Any, str]] = []
    for label, name in SIMULATED.items():
        jobs.append((label, name, "recorded"))
        jobs.append((label, name, "simulated"))
    jobs += [(k, v, "auto") for k, v in REAL.items() if (DATA / v[0]).exists()]
    if args.only:
        keys = [k.strip().lower() for k in args.only.split(",") if k.strip()]
        jobs = [j for j in jobs if any(k in j[0].lower() for k in keys)]
    rows = []
    for label, spec, odo in jobs:
        t0 = time.perf_counter()
        cfg = RunConfig(backend="frontend", odometry=odo)
        if isinstance(spec, str):
            seq = simulate(spec, seed=args.seed, duration=args.duration)
        else:
            rel, kw = spec
            seq = read_sequence(DATA / rel, **kw)
            guard = GuardConfig(odometry_initial_guess=args.real_initial_guess == "odometry")
            cfg = RunConfig(backend="frontend", odometry=odo, max_scans=args.max_scans, guard=guard)
        res = run_recording(
            seq,
            det,
            out / f"{seq.name}_{odo}",
            config=cfg,
            baseline=judge,
            baseline_info=judge_info,
        )
        e = res.errors
        rows.append(
            {
                "label": label,
                "scans": res.n_scans,
                "odometry": res.odometry_source.replace("simulated_from_reference", "simulated"),
                "rpe": {k: e[k]["rpe_trans_rmse"] for k in e},
                "red": {
                    k: res.rpe_reduction(k)
                    for k in ("frontend+cnn", "frontend+baseline", "frontend+oracle")
                },
                "cent": res.centroid,
                "acc": {k: g.accuracy for k, g in res.gates.items()},
            }
        )
        print(f"done {label} [{odo}] in {time.perf_counter() - t0:.0f} s", flush=True)
    lines = [
        f"Baseline: {judge_info}.",
        "",
        "| sequence | scans | odometry | RPE odom (m) | RPE ICP (m) | RPE ICP+CNN (m) | "
        "RPE ICP+baseline (m) | RPE ICP+oracle (m) | reduction CNN / baseline / oracle "
        "(paper: 75 %) | gate accuracy CNN / baseline | centroid dist. ICP / CNN / oracle (m) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rpe, red, c, acc = r["rpe"], r["red"], r["cent"], r["acc"]
        lines.append(
            f"| {r['label']} | {r['scans']} | {r['odometry']} | {rpe['odometry']:.4f} | "
            f"{rpe['frontend']:.4f} | {rpe['frontend+cnn']:.4f} | {rpe['frontend+baseline']:.4f} | "
            f"{rpe['frontend+oracle']:.4f} | {100 * red['frontend+cnn']:.0f} % / "
            f"{100 * red['frontend+baseline']:.0f} % / {100 * red['frontend+oracle']:.0f} % | "
            f"{acc.get('cnn', float('nan')):.3f} / {acc.get('baseline', float('nan')):.3f} | "
            f"{c['frontend']:.3f} / {c['frontend+cnn']:.3f} / {c['frontend+oracle']:.3f} |"
        )
    table = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "slam_gain.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
