"""Learned loop-closure judge: harvest, training and the held-out table, in one command.

1. Harvest every loop-closure candidate of the ``graph`` back end (reference judge, so the graph
   stays right) on ``--scenarios`` x (``--train-seeds`` + ``--test-seeds``), with features and
   reference labels (`scanguard.slam.graph.harvest`); cached in ``--cache`` (resumable per
   scenario and seed).
2. Fit, on the training seeds only: the learned judge (threshold and model kind chosen on
   leave-one-sequence-out validation predictions) and the classical test with a disagreement
   gate (`scanguard.slam.graph.learn.fit_classical`).
3. Evaluate on the held-out seeds (never used for fitting or thresholds): the learned judge,
   the fitted classical test, the classical defaults, accept-all and the shipped sequential
   CNN as it is. Positive class = fault (a rejected candidate).
4. Write the judge file (``--model``; the shipped one by default, not with ``--quick``) with
   its provenance and the held-out table, and print the table (markdown).

Run: python benchmarks/closure_judge.py [--quick] [--jobs 2]
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from scanguard.slam.graph.closure import ClosureJudgeConfig  # noqa: E402
from scanguard.slam.graph.harvest import (  # noqa: E402
    harvest_table,
    labelled,
    merge_caches,
    select,
)
from scanguard.slam.graph.learn import (  # noqa: E402
    CLASSICAL_RULE,
    THRESHOLD_RULE,
    ClassicalClosureTest,
    LearnedClosureJudge,
    default_judge_path,
    fit_classical,
    save_closure_judge,
)

log = logging.getLogger("closure_judge")

SCENARIOS = ("twin_rooms", "twin_corridors", "crowd_closure", "office", "mixed_loop", "crowd_stop")


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def _harvest_part(args: tuple[list[str], list[int], str, bool]) -> dict[str, Any]:
    scenarios, seeds, cache, cnn = args
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    detector = None
    if cnn:
        from scanguard.detect.detector import FaultDetector

        detector = FaultDetector.load()
    return harvest_table(scenarios, seeds, cache=cache, detector=detector)


def harvest(
    scenarios: list[str], seeds: list[int], cache: Path, cnn: bool, jobs: int
) -> dict[str, Any]:
    """The candidate table, harvested by ``jobs`` processes (one cache file each, merged)."""
    if jobs <= 1 or cache.is_file():
        return _harvest_part((scenarios, seeds, str(cache), cnn))
    parts = [scenarios[i::jobs] for i in range(jobs)]
    work = [
        (p, seeds, str(cache.with_name(f"{cache.stem}.{i}{cache.suffix}")), cnn)
        for i, p in enumerate(parts)
        if p
    ]
    with ProcessPoolExecutor(len(work)) as pool:
        list(pool.map(_harvest_part, work))
    merge_caches([Path(w[2]) for w in work], cache)
    return _harvest_part((scenarios, seeds, str(cache), cnn))


def metrics(y: np.ndarray, reject: np.ndarray, score: np.ndarray | None) -> dict[str, float]:
    """Accuracy, balanced accuracy, fault precision / recall, ROC AUC, accepted faults."""
    from sklearn.metrics import roc_auc_score

    fault = y == 1
    tp = int((reject & fault).sum())
    fp = int((reject & ~fault).sum())
    fn = int((~reject & fault).sum())
    tn = int((~reject & ~fault).sum())
    s = reject.astype(np.float64) if score is None else score
    both = fault.any() and (~fault).any()
    return {
        "accuracy": (tp + tn) / len(y),
        "balanced_accuracy": 0.5 * (tp / max(tp + fn, 1) + tn / max(tn + fp, 1)),
        "precision": tp / (tp + fp) if tp + fp else math.nan,
        "recall": tp / (tp + fn) if tp + fn else math.nan,
        "roc_auc": float(roc_auc_score(fault, s)) if both else math.nan,
        "faults_accepted": fn,
        "normals_accepted": tn,
        "n_fault": int(fault.sum()),
        "n_normal": int((~fault).sum()),
    }


def _fmt(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.3f}"


def markdown(rows: dict[str, dict[str, float]]) -> str:
    """The held-out table as markdown."""
    head = (
        "| judge | accuracy | balanced acc. | precision (fault) | recall (fault) | ROC AUC "
        "| faults accepted | normals accepted |\n|---|---|---|---|---|---|---|---|\n"
    )
    body = ""
    for name, m in rows.items():
        body += (
            f"| {name} | {_fmt(m['accuracy'])} | {_fmt(m['balanced_accuracy'])} | "
            f"{_fmt(m['precision'])} | {_fmt(m['recall'])} | {_fmt(m['roc_auc'])} | "
            f"{m['faults_accepted']} / {m['n_fault']} | {m['normals_accepted']} / "
            f"{m['n_normal']} |\n"
        )
    return head + body


def evaluate(
    test: dict[str, Any],
    learned: LearnedClosureJudge,
    classical: ClassicalClosureTest,
    cnn_threshold: float | None,
) -> dict[str, dict[str, float]]:
    """Rows of the held-out table."""
    y = np.asarray(test["label"]).astype(np.int64)
    rows: dict[str, dict[str, float]] = {}
    p = learned.predict_proba(test)
    rows[f"learned ({learned.model.kind})"] = metrics(y, p >= learned.threshold, p)
    rows["classical, fitted (+ disagreement gate)"] = metrics(y, ~classical.passes(test), None)
    d = ClosureJudgeConfig()
    default = ClassicalClosureTest(
        d.classical_min_response, d.classical_max_std_xy, d.classical_max_std_theta
    )
    rows["classical, defaults"] = metrics(y, ~default.passes(test), None)
    resp = np.asarray(test["response"], dtype=np.float64)
    rows["response alone (AUC of -response)"] = metrics(
        y, ~default.passes(test), -np.nan_to_num(resp, nan=0.0)
    )
    rows["accept all (none)"] = metrics(y, np.zeros(len(y), dtype=bool), None)
    if "cnn_proba" in test and cnn_threshold is not None:
        c = np.asarray(test["cnn_proba"], dtype=np.float64)
        rows["shipped sequential CNN as is"] = metrics(y, c >= cnn_threshold, c)
    return rows


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--train-seeds", default="0,1,2")
    ap.add_argument("--test-seeds", default="3,4")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "closure_candidates.npz")
    ap.add_argument("--model", type=Path, default=None, help="judge file to write")
    ap.add_argument("--no-cnn", action="store_true", help="skip the shipped CNN column")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="3 traps, seeds 0,1 / 3; no model")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")

    scenarios = args.scenarios.split(",")
    train_seeds, test_seeds = _ints(args.train_seeds), _ints(args.test_seeds)
    model_path: Path | None = args.model
    if args.quick:
        scenarios = ["twin_rooms", "twin_corridors", "crowd_closure"]
        train_seeds, test_seeds = [0, 1], [3]
        args.cache = args.cache.with_name("closure_candidates_quick.npz")
    elif model_path is None:
        model_path = default_judge_path()
    if set(train_seeds) & set(test_seeds):
        ap.error("train and test seeds overlap")

    table = harvest(scenarios, train_seeds + test_seeds, args.cache, not args.no_cnn, args.jobs)
    table = labelled(table)
    seeds = np.asarray(table["seed"])
    train = select(table, np.isin(seeds, train_seeds))
    test = select(table, np.isin(seeds, test_seeds))
    groups = np.char.add(np.char.add(train["scenario"].astype(str), ":"), train["seed"].astype(str))
    log.info("train: %d candidates, test: %d", len(train["label"]), len(test["label"]))

    learned = LearnedClosureJudge.fit(train, groups)
    classical = fit_classical(train)
    cnn_threshold = None
    if "cnn_proba" in table:
        from scanguard.detect.detector import FaultDetector

        cnn_threshold = float(FaultDetector.load().threshold)
    rows = evaluate(test, learned, classical, cnn_threshold)
    text = markdown(rows)
    print(text)

    def counts(t: dict[str, Any]) -> dict[str, dict[str, int]]:
        out = {}
        for name in sorted(set(t["scenario"].astype(str))):
            lab = t["label"][t["scenario"] == name]
            out[name] = {"normal": int((lab == 0).sum()), "fault": int((lab == 1).sum())}
        return out

    print("held-out per scenario (faults accepted: learned / classical fitted / of faults):")
    for name in sorted(set(test["scenario"].astype(str))):
        sub = select(test, test["scenario"] == name)
        y = sub["label"] == 1
        pl = learned.predict_proba(sub) >= learned.threshold
        pc = ~classical.passes(sub)
        print(
            f"  {name}: {int((y & ~pl).sum())} / {int((y & ~pc).sum())} / {int(y.sum())}; "
            f"normals accepted {int((~y & ~pl).sum())} / {int((~y & ~pc).sum())} / "
            f"{int((~y).sum())}"
        )
    if model_path is not None:
        prov = {
            "issue": 12,
            "scenarios": scenarios,
            "train_seeds": train_seeds,
            "test_seeds_held_out": test_seeds,
            "train_counts": counts(train),
            "test_counts": counts(test),
            "labels": ClosureJudgeConfig().labels.model_dump(),
            "threshold": learned.threshold,
            "threshold_rule": THRESHOLD_RULE,
            "classical_rule": CLASSICAL_RULE,
            "held_out": rows,
            "command": "python benchmarks/closure_judge.py",
        }
        path = save_closure_judge(model_path, learned, classical, prov)
        log.info("wrote %s", path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
