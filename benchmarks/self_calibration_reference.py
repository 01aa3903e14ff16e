"""Self-calibration and the zero-shot judge against manually verified labels (issue 29).

    python benchmarks/self_calibration_reference.py [--work runs/selfcal-ref] [--max-scans 2000]
        [--max-dt 2]

Protocol (the shipped ``plicp`` model, the default run's matcher; figures in README,
"Self-calibration against verified relations"):

1. **Held-out pairs with a reference.** `relation_pairs.py`: every relation of the three
   Freiburg benchmark logs at most ``--max-dt`` seconds long (a median 4-8 raw scans apart)
   is one pair of raw scans, matched by plicp seeded with the raw wheel increment (as the
   default run seeds it) and labelled by the model's label rule against the relation, which
   was verified by hand (Kümmerle et al. 2009). The self-calibration never reads them.
2. **`scanguard calibrate --self LOG --max-scans N`** on each raw log (no reference, no
   relations): its first pass, its self-supervised labels, its refitted calibration, as
   shipped. Its ``model.pt`` judges the held-out pairs.
3. **Threshold rules on the self-supervised labels.** The same first pass labels the
   consecutive pairs of the first N scans (self-supervised: `dataset build --reference
   first_pass_trajectory.tum`); each rule picks a threshold of the shipped model's
   probability on them: ``shipped`` (no change), ``max_ba`` (the project rule, what
   ``calibrate --self`` does), ``max_accuracy``, ``max_f1``, ``spec_0.95`` / ``0.98`` /
   ``0.99`` (the lowest threshold whose self-label specificity reaches that). A temperature
   does not change the ranking, so a threshold of the raw probability is the whole effect.
4. **Leave one log out**: each fold picks the rule with the largest mean balanced accuracy
   on the held-out pairs of the two other logs and is measured on the third.

Prints markdown tables: zero-shot and ``calibrate --self`` per log, then every rule, then the
folds. Everything is cached in ``--work`` (a rerun only prints).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from relation_pairs import BENCH, LOGS, build

from scanguard.config import save_config
from scanguard.dataset import DatasetConfig
from scanguard.detect.detector import FaultDetector
from scanguard.detect.evaluate import evaluate_store
from scanguard.pairs.labels import LabelConfig

ROOT = Path(__file__).resolve().parents[1]
RULES = ("shipped", "max_ba", "max_accuracy", "max_f1", "spec_0.95", "spec_0.98", "spec_0.99")


def _scanguard() -> str:
    exe = Path(sys.executable).with_name("scanguard")
    return str(exe) if exe.exists() else "scanguard"


def scores(det: FaultDetector, store: Path) -> tuple[np.ndarray, np.ndarray]:
    """(labels, fault probabilities) of a store's labelled pairs."""
    r = evaluate_store(det, store, splits=None, baselines=[], backend="onnx")
    y = np.asarray(r.labels)
    s = np.asarray(r.methods[0].scores)
    keep = y >= 0
    return y[keep], s[keep]


def stats(y: np.ndarray, s: np.ndarray, t: float) -> dict[str, float]:
    """Accuracy, balanced accuracy, specificity and recall at threshold ``t``."""
    flag = s >= t
    pos, neg = y == 1, y == 0
    rec = float((flag & pos).sum() / max(pos.sum(), 1))
    spec = float((~flag & neg).sum() / max(neg.sum(), 1))
    acc = float(((flag & pos) | (~flag & neg)).sum() / max(len(y), 1))
    return {"acc": acc, "ba": 0.5 * (rec + spec), "spec": spec, "recall": rec}


def auc(y: np.ndarray, s: np.ndarray) -> float:
    """Area under the ROC curve (ties count half)."""
    pos, neg = s[y == 1], s[y == 0]
    if not len(pos) or not len(neg):
        return float("nan")
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def rule_threshold(rule: str, y: np.ndarray, s: np.ndarray, shipped: float) -> float:
    """The threshold ``rule`` picks on self-supervised labels ``y`` (ties: closest to 0.5)."""
    if rule == "shipped":
        return shipped
    ts = np.unique(np.concatenate([s, [shipped]]))
    if rule.startswith("spec_"):
        ok = [t for t in ts if stats(y, s, t)["spec"] >= float(rule[5:])]
        return float(min(ok)) if ok else 1.0
    if rule == "max_f1":

        def key(t: float) -> tuple[float, float]:
            tp = ((s >= t) & (y == 1)).sum()
            return 2 * tp / max((s >= t).sum() + (y == 1).sum(), 1), -abs(t - 0.5)

    else:
        col = {"max_ba": "ba", "max_accuracy": "acc"}[rule]

        def key(t: float) -> tuple[float, float]:
            return stats(y, s, t)[col], -abs(t - 0.5)

    return float(max(ts, key=key))


def prepare(work: Path, name: str, max_scans: int, max_dt: float, det: FaultDetector) -> None:
    """Relation pairs, ``calibrate --self`` and the self-labelled pairs of one log (cached)."""
    labels = LabelConfig(**det.label_thresholds)
    rel = work / "relations"
    rel.mkdir(parents=True, exist_ok=True)
    if not (rel / f"{name}.h5").exists():
        build(name, rel, "plicp", labels, max_dt)
    log = str(BENCH / f"{name}.clf.gz")
    cal = work / f"self_{name}"
    if not (cal / "model.pt").exists():
        cmd = [_scanguard(), "calibrate", "--self", log, "--max-scans", str(max_scans)]
        subprocess.run([*cmd, "-o", str(cal)], check=True, capture_output=True)
    data = {"name": "self_labels", "matcher": "plicp", "recording_initial_guess": "odometry",
            "labels": labels.model_dump()}  # fmt: skip
    cfg = save_config(DatasetConfig.from_dict(data), work, "self_labels.yaml")
    out = work / f"self_labels_{name}"
    if not (out / "manifest.json").exists():
        ref = str(cal / "first_pass_trajectory.tum")
        cmd = [_scanguard(), "dataset", "build", "-c", str(cfg), "-r", log, "--reference", ref]
        subprocess.run([*cmd, "--max-scans", str(max_scans), "-o", str(out)], check=True,
                       capture_output=True)  # fmt: skip


def _row(m: dict[str, float]) -> str:
    return f"{m['acc']:.3f} / {m['ba']:.3f} / {m['spec']:.3f} / {m['recall']:.3f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "selfcal-ref")
    ap.add_argument("--max-scans", type=int, default=2000)
    ap.add_argument("--max-dt", type=float, default=2.0)
    args = ap.parse_args()
    det = FaultDetector.load(None, backend="onnx", matcher="plicp")
    held: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    picks: dict[tuple[str, str], dict[str, float]] = {}
    print("| log | held-out pairs (normal / fault) | AUC | zero-shot, fixed 0.256 | "
          "`calibrate --self` (its threshold) |")  # fmt: skip
    print("|---|---|---|---|---|")
    for name in LOGS:
        prepare(args.work, name, args.max_scans, args.max_dt, det)
        y, s = scores(det, args.work / "relations" / f"{name}.h5")
        held[name] = (y, s)
        own = FaultDetector.load(args.work / f"self_{name}" / "model.pt", backend="onnx")
        ys, ss = scores(own, args.work / "relations" / f"{name}.h5")
        print(f"| {name} | {(y == 0).sum()} / {(y == 1).sum()} | {auc(y, s):.3f} | "
              f"{_row(stats(y, s, det.threshold))} | {_row(stats(ys, ss, own.threshold))} "
              f"({own.threshold:.3f}) |")  # fmt: skip
        yl, sl = scores(det, args.work / f"self_labels_{name}")
        for rule in RULES:
            t = rule_threshold(rule, yl, sl, det.threshold)
            picks[(name, rule)] = {"t": t, **stats(y, s, t)}
    print("\nacc / BA / spec / recall on the held-out pairs; threshold in brackets\n")
    print("| rule | " + " | ".join(LOGS) + " |")
    print("|---|" + "---|" * len(LOGS))
    for rule in RULES:
        cells = [f"{_row(picks[(n, rule)])} ({picks[(n, rule)]['t']:.3f})" for n in LOGS]
        print(f"| {rule} | " + " | ".join(cells) + " |")
    print("\n| held out | chosen on the others (mean BA) | held-out acc / BA / spec / recall |")
    print("|---|---|---|")
    for name in LOGS:
        others = [n for n in LOGS if n != name]
        best = max(RULES, key=lambda r: np.mean([picks[(n, r)]["ba"] for n in others]))
        print(f"| {name} | {best} | {_row(picks[(name, best)])} |")


if __name__ == "__main__":
    main()
