"""Learned loop-closure judge: harvest, training and the held-out table, in one command.

1. Harvest every loop-closure candidate of the ``graph`` back end (reference judge, so the graph
   stays right) on ``--scenarios`` x (``--train-seeds`` + ``--test-seeds``), with features and
   reference labels (`scanguard.apps.closure_harvest`); cached in ``--cache`` (resumable per
   scenario and seed).
2. Fit, on the training seeds only: the learned judge (threshold and model kind chosen on
   leave-one-sequence-out validation predictions) and the classical test with a disagreement
   gate (`scanguard.apps.closure_judge.fit_classical`).
3. Evaluate on the held-out seeds (never used for fitting or thresholds): the learned judge,
   the fitted classical test, the classical defaults, accept-all and the shipped sequential
   CNN as it is. Positive class = fault (a rejected candidate). With ``--closed-loop``, also
   run the held-out sequences with each judge deciding (accepted faults, trajectory error).
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

from scanguard.apps.closure_harvest import (  # noqa: E402
    harvest_table,
    labelled,
    merge_caches,
    select,
)
from scanguard.apps.closure_judge import (  # noqa: E402
    CLASSICAL_RULE,
    THRESHOLD_RULE,
    fit_classical,
    fit_learned_judge,
)
from scanguard.slam.graph.closure import (  # noqa: E402
    AcceptAll,
    ClosureJudgeConfig,
    ResponseTest,
)
from scanguard.slam.graph.judges import (  # noqa: E402
    LEARNED_FEATURES,
    ClassicalClosureTest,
    LearnedClosureJudge,
    default_judge_path,
    save_closure_judge,
)

log = logging.getLogger("closure_judge")

SCENARIOS = (
    "twin_rooms",
    "twin_corridors",
    "crowd_closure",
    "crowd_stop",
    "mixed_loop",
)
LOOP_SCENARIOS = ("twin_rooms", "twin_corridors", "crowd_closure", "mixed_loop")


SCAN_ONLY = tuple(
    f for f in LEARNED_FEATURES if not f.startswith("disagreement") and f != "path_gap"
)
"""The learned features without the graph's (what the scan pair alone tells)."""


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def _harvest_part(args: tuple[list[str], list[int], str, bool]) -> dict[str, Any]:
    scenarios, seeds, cache, cnn = args
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    detector = None
    if cnn:
        from scanguard.detect.detector import FaultDetector

        detector = FaultDetector.load()
    return harvest_table(scenarios, seeds, cache=cache, detector=detector, simulate_fn=_simulate)


SLIP = "+slip"
"""Suffix of a scenario run with the demo scene's wheel slips (``--slip``)."""


def _simulate(name: str, *, seed: int) -> Any:
    """`scanguard.sim.simulate`; a name ending in `SLIP` adds the demo scene's wheel slips."""
    from scanguard.sim import load_scenario, simulate

    if name.endswith(SLIP):
        odo = load_scenario("office_slip").odometry
        return simulate(
            name[: -len(SLIP)],
            seed=seed,
            odometry__slip_every=odo.slip_every,
            odometry__slip_duration=odo.slip_duration,
            odometry__slip_speed=odo.slip_speed,
        )
    return simulate(name, seed=seed)


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


def _closed_loop_one(args: tuple[str, int, str, Any]) -> dict[str, Any]:
    """One graph run of a held-out sequence with a judge: closures and trajectory error."""
    from scanguard.geometry import compose
    from scanguard.sim import simulate
    from scanguard.slam.graph import GraphBackend, GraphConfig, ReferenceClosureJudge

    name, seed, judge_name, judge = args
    seq = simulate(name, seed=seed)
    if judge is None:
        judge = ReferenceClosureJudge(compose(seq.reference, seq.laser_offset))
    b = GraphBackend(
        GraphConfig(),
        laser_offset=seq.laser_offset,
        initial_pose=seq.reference[0],
        range_max=float(seq.sensor.range_max),
        closure_judge=judge,
        reference=seq.reference,
    )
    for i, scan in enumerate(seq.scans):
        b.update(scan, seq.odometry[i])
    traj = b.trajectory()
    err = np.hypot(*(traj[:, :2] - np.asarray(seq.reference)[:, :2]).T)
    added = [r for r in b.closures if r.added]
    return {
        "scenario": name,
        "seed": seed,
        "judge": judge_name,
        "candidates": len(b.closures),
        "accepted_fault": sum(r.label == 1 for r in added),
        "accepted_normal": sum(r.label == 0 for r in added),
        "accepted_ambiguous": sum(r.label == -1 for r in added),
        "ate_rmse": float(np.sqrt(np.mean(err**2))),
        "max_error": float(err.max()),
    }


def closed_loop(
    scenarios: list[str], seeds: list[int], judges: dict[str, Any], jobs: int
) -> list[dict[str, Any]]:
    """Graph runs of the held-out sequences with each judge in the loop."""
    work = [(n, s, j, judge) for n in scenarios for s in seeds for j, judge in judges.items()]
    if jobs <= 1:
        return [_closed_loop_one(w) for w in work]
    with ProcessPoolExecutor(jobs) as pool:
        return list(pool.map(_closed_loop_one, work))


def closed_loop_markdown(results: list[dict[str, Any]], judges: list[str]) -> str:
    """Per judge: accepted faults / normals and trajectory error, summed over sequences."""
    text = (
        "| judge in the loop | candidates | faults accepted | normals accepted "
        "| sequences with a fault accepted | mean ATE RMSE (m) | worst max error (m) |\n"
        "|---|---|---|---|---|---|---|\n"
    )
    for j in judges:
        rs = [r for r in results if r["judge"] == j]
        text += (
            f"| {j} | {sum(r['candidates'] for r in rs)} | "
            f"{sum(r['accepted_fault'] for r in rs)} | {sum(r['accepted_normal'] for r in rs)} | "
            f"{sum(r['accepted_fault'] > 0 for r in rs)} / {len(rs)} | "
            f"{np.mean([r['ate_rmse'] for r in rs]):.3f} | "
            f"{max(r['max_error'] for r in rs):.3f} |\n"
        )
    return text


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
    scan_only: LearnedClosureJudge | None = None,
) -> dict[str, dict[str, float]]:
    """Rows of the held-out table."""
    y = np.asarray(test["label"]).astype(np.int64)
    rows: dict[str, dict[str, float]] = {}
    p = learned.predict_proba(test)
    rows[f"**learned** ({learned.model.kind})"] = metrics(y, p >= learned.threshold, p)
    if scan_only is not None:
        q = scan_only.predict_proba(test)
        rows[f"learned, scan evidence only ({scan_only.model.kind})"] = metrics(
            y, q >= scan_only.threshold, q
        )
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


def counts(t: dict[str, Any]) -> dict[str, dict[str, int]]:
    """Normal and fault candidates per scenario."""
    out = {}
    for name in sorted(set(t["scenario"].astype(str))):
        lab = t["label"][t["scenario"] == name]
        out[name] = {"normal": int((lab == 0).sum()), "fault": int((lab == 1).sum())}
    return out


def print_per_scenario(
    test: dict[str, Any], learned: LearnedClosureJudge, classical: ClassicalClosureTest
) -> None:
    """Held-out faults and normals accepted per scenario, learned and classical."""
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


def _parser() -> argparse.ArgumentParser:
    """The command line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--train-seeds", default="0,1,2")
    ap.add_argument("--test-seeds", default="3,4")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "closure_candidates_v2.npz")
    ap.add_argument("--model", type=Path, default=None, help="judge file to write")
    ap.add_argument("--no-cnn", action="store_true", help="skip the shipped CNN column")
    ap.add_argument(
        "--features",
        default=",".join(LEARNED_FEATURES),
        help="the learned judge's columns (comma-separated; default: the shipped judge's)",
    )
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="3 traps, seeds 0,1 / 3; no model")
    ap.add_argument(
        "--closed-loop", action="store_true", help="also run the held-out sequences per judge"
    )
    ap.add_argument("--closed-loop-scenarios", default=",".join(LOOP_SCENARIOS))
    ap.add_argument(
        "--slip",
        action="store_true",
        help="also harvest every scenario with wheel slips (a graph that drifts unawares)",
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    ap = _parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")

    scenarios = args.scenarios.split(",")
    if args.slip:
        scenarios += [f"{n}{SLIP}" for n in scenarios]
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

    learned = fit_learned_judge(train, groups, features=args.features.split(","))
    scan_only = fit_learned_judge(train, groups, features=SCAN_ONLY)
    classical = fit_classical(train)
    cnn_threshold = None
    if "cnn_proba" in table:
        from scanguard.detect.detector import FaultDetector

        cnn_threshold = float(FaultDetector.load().threshold)
    rows = evaluate(test, learned, classical, cnn_threshold, scan_only)
    text = markdown(rows)
    print(text)

    print_per_scenario(test, learned, classical)
    loop_rows: list[dict[str, Any]] = []
    if args.closed_loop:
        d = ClosureJudgeConfig()
        judges: dict[str, Any] = {
            "none": AcceptAll(),
            "classical, defaults": ResponseTest.from_config(d),
            "classical, fitted": classical,
            "learned": learned,
            "oracle": None,
        }
        loop_scen = [n for n in args.closed_loop_scenarios.split(",") if n in scenarios]
        loop_rows = closed_loop(loop_scen, test_seeds, judges, args.jobs)
        print(closed_loop_markdown(loop_rows, list(judges)))
        for r in loop_rows:
            log.info("closed loop: %s", r)
    if model_path is not None:
        prov = {
            "issue": 30,
            "features": list(learned.features),
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
            "held_out_closed_loop": loop_rows,
            "command": " ".join(["python benchmarks/closure_judge.py", *(argv or sys.argv[1:])]),
        }
        path = save_closure_judge(model_path, learned, classical, prov)
        log.info("wrote %s", path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
