"""SLAM gain table: RPE of plain ICP vs ICP gated by the CNN (and the oracle upper bound).

Runs `scanguard.slam_run.run_recording` on the simulated Environments 1-5 and on the shared
real recordings, then prints one markdown table (also written to ``<out>/slam_gain.md``):
per sequence the RPE (translation RMSE per scan pair, evo) of plain ICP, CNN-gated ICP and
oracle-gated ICP, and the reduction against plain ICP next to the paper's 75 % (its Fig. 19).

    python benchmarks/slam_gain.py [--model PATH] [--duration 30] [--out /tmp/slam_gain]

Needs a trained model (default: the shipped one).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scanguard.detector import FaultDetector
from scanguard.io import read_sequence
from scanguard.sim import simulate
from scanguard.slam_run import RunConfig, run_recording

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SIMULATED = {
    "Env 1 lobby (sim)": "lobby",
    "Env 2 corridor (sim)": "corridor",
    "Env 3 glass (sim)": "glass",
    "Env 4 hall (sim)": "hall",
    "Env 5 office (sim)": "office",
}
REAL = {
    "Intel lab (CARMEN)": ("carmen/intel-corrected.log.gz", {}),
    "ACES (CARMEN)": ("carmen/aces-corrected.log.gz", {}),
    "CSAIL (CARMEN)": ("carmen/csail-corrected.log.gz", {}),
    "FR079 (CARMEN, first 1500)": ("carmen/freiburg-079-corrected.log.gz", {}),
    "leg_tracker (static)": (
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
    args = ap.parse_args()
    det = FaultDetector.load(args.model)
    out = Path(args.out)
    rows = []
    jobs: list[tuple[str, object]] = [(k, v) for k, v in SIMULATED.items()]
    jobs += [(k, v) for k, v in REAL.items() if (DATA / v[0]).exists()]
    for label, spec in jobs:
        cfg = RunConfig()
        if isinstance(spec, str):
            seq = simulate(spec, seed=args.seed, duration=args.duration)
        else:
            rel, kw = spec  # type: ignore[misc]
            seq = read_sequence(DATA / rel, **kw)
            if "freiburg" in rel:
                cfg = RunConfig(max_scans=1500)
        res = run_recording(seq, det, out / seq.name, config=cfg)
        e = res.errors
        rows.append(
            (
                label,
                res.n_scans,
                res.odometry_source,
                e["icp"]["rpe_trans_rmse"],
                e["icp+cnn"]["rpe_trans_rmse"],
                e["icp+oracle"]["rpe_trans_rmse"],
                res.rpe_reduction("icp+cnn"),
                res.rpe_reduction("icp+oracle"),
                res.centroid["icp"],
                res.centroid["icp+cnn"],
            )
        )
        print(f"done {label}", flush=True)
    lines = [
        "| sequence | scans | odometry | RPE ICP (m) | RPE ICP+CNN (m) | RPE ICP+oracle (m) | "
        "CNN reduction | oracle reduction | paper | centroid ICP / ICP+CNN (m) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.4f} | {r[4]:.4f} | {r[5]:.4f} | "
            f"{100 * r[6]:.0f} % | {100 * r[7]:.0f} % | 75 % | {r[8]:.3f} / {r[9]:.3f} |"
        )
    table = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "slam_gain.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
