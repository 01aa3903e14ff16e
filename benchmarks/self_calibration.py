"""How often the shipped detector rejects matches on the static Freiburg logs, with the
odometry noise model it was trained with and with the one fitted to each log (self-calibration,
`scanguard.apps.self_calibration`; no reference, no relations).

    python benchmarks/self_calibration.py [--pairs 600] [--matcher icp-paper]

For each log: the fit uses 300 consecutive pairs spread over the log; the rejection rate is
measured on ``--pairs`` other consecutive pairs, spread over the log and interleaved with the
fitting ones (never the same pair). The Freiburg logs are static (a few people at most), so a
rejection there is mostly an over-flag: issue 21's target is at most 10 % of the judged scans.
Prints one row per log and detector setting, and the ratio fitted / default.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from scanguard.apps.self_calibration import fit_robot_noise
from scanguard.detect.detector import FaultDetector
from scanguard.geometry import relative
from scanguard.io import read_sequence
from scanguard.matching.registry import get_matcher
from scanguard.slam.grid import robot_to_sensor_increment

BENCH = Path(__file__).resolve().parents[2] / "shared" / "data" / "benchmark"
LOGS = ("intel", "fr079", "aces")


def rejection_rate(det: FaultDetector, seq, matcher, picks) -> tuple[float, int]:
    flagged = judged = 0
    for k in picks:
        prev, cur = seq.scans[k], seq.scans[k + 1]
        if int(prev.valid.sum()) < 10 or int(cur.valid.sum()) < 10:
            continue
        m = matcher(cur.points(np.float64), prev.points(np.float64), None)
        odo = robot_to_sensor_increment(
            relative(seq.odometry[k], seq.odometry[k + 1]), seq.laser_offset
        )
        p = det.fault_probability(prev, cur, m.pose, match=m, odometry=odo)
        flagged += int(not (p < det.threshold))
        judged += 1
    return flagged / max(judged, 1), judged


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=600)
    ap.add_argument("--matcher", default="icp-paper")
    args = ap.parse_args()
    matcher = get_matcher(args.matcher)
    print(
        "| log | pairs judged | rejected, trained noise | rejected, fitted noise | "
        "fitted scales (trans, rot) | ratio |"
    )
    print("|---|---|---|---|---|---|")
    for name in LOGS:
        seq = read_sequence(BENCH / f"{name}.clf.gz")
        n = len(seq)
        # judged pairs: an even spread, shifted by half a step from the fitting pairs
        step = (n - 2) / args.pairs
        picks = np.unique((np.arange(args.pairs) * step + step / 2).astype(np.int64))
        det = FaultDetector.load(matcher=args.matcher)
        before, judged = rejection_rate(det, seq, matcher, picks)
        fit = fit_robot_noise(seq, seq.odometry, matcher, det.odometry_noise)
        det.use_odometry_noise(fit.noise)
        after, _ = rejection_rate(det, seq, matcher, picks)
        ratio = after / before if before else float("nan")
        print(
            f"| {name} | {judged} | {100 * before:.1f} % | {100 * after:.1f} % | "
            f"x{fit.trans_scale:.2f}, x{fit.rot_scale:.2f} | {ratio:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
