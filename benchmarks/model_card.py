"""Regenerate every table and figure of the detector's model card, for one matcher.

    python benchmarks/model_card.py --matcher icp-paper [--loeo] [--ship]

One command, resumable (every stage skips what is already on disk):

1. **Data** (`scanguard dataset build`, matcher ``--matcher``): the simulated
   ``configs/transfer.yaml`` (paper E1-4, domain-randomised E1-4, the office E5 held out) and
   the shared real recordings with a reference (four CARMEN corrected logs, the static
   leg_tracker bag), labelled with one policy (`scanguard.dataset.labelling.resolve_initial_guess`).
2. **Model** (`scanguard train -c configs/train_transfer.yaml`) on the train split of the
   simulated data; with ``--loeo`` one more model per environment E of E1-4, trained without E
   and its randomised twin.
3. **Scores** of the CNN (fault logit) and of every classical detector
   (`scanguard.detect.baselines.registry.BASELINES` + `ODOMETRY_BASELINES`, fitted on the same train
   split) on every evaluation pair.
4. **Held-out protocol** (`scanguard.detect.protocol.evaluate_heldout`): each figure's
   threshold (and the CNN's Platt calibration) comes from *selection* pairs that are neither
   training data nor the pairs of the figure, the same pairs and rule for every method:

   | figure | evaluation pairs | selection pairs |
   |---|---|---|
   | E1-4 (and randomised) test | test split | office + every real recording |
   | office | every office pair | every real recording |
   | real recording r | every pair of r | office + the other recordings (leave one out) |
   | LOEO E | every pair of E (model trained without E) | office + every real recording |

5. **Outputs** in ``--out`` (default ``docs/model_card/<matcher>``): ``tables.md``,
   ``results.json`` (with the command line), ``roc.png``, ``reliability.png``. With
   ``--ship`` the model calibrated on office + every real recording is written into the
   package (``scanguard/models/default.pt`` for ``icp-paper``, else ``<matcher>.pt``) together
   with the classical detector that scored best on those pairs (``baseline.json`` /
   ``baseline-<matcher>.json``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np

from scanguard.dataset import PairStore
from scanguard.detect.baselines.metrics_model import MetricsModelDetector
from scanguard.detect.baselines.registry import (
    BASELINES,
    ODOMETRY_BASELINES,
    make_baseline,
    save_detector,
)
from scanguard.detect.calibrate import fit_calibration, plot_reliability
from scanguard.detect.detector import FaultDetector
from scanguard.detect.features import store_features
from scanguard.detect.images import render_all
from scanguard.detect.protocol import evaluate_heldout
from scanguard.detect.recalibrate import save_calibrated
from scanguard.detect.train_config import TrainConfig
from scanguard.fsutil import atomic_path, atomic_write_text, save_figure
from scanguard.logging_utils import configure_logging

log = logging.getLogger("model_card")
ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
PAPER_ENVS = {"lobby": "E1", "corridor": "E2", "glass": "E3", "hall": "E4"}
OFFICE = "office"
#: Real recordings with a reference: (file, extra `dataset build` options, store folder name).
RECORDINGS: list[tuple[str, list[str], str]] = [
    ("carmen/intel-corrected.log.gz", [], "real"),
    ("carmen/aces-corrected.log.gz", [], "real"),
    ("carmen/csail-corrected.log.gz", [], "real"),
    ("carmen/freiburg-079-corrected.log.gz", [], "real"),
    (
        "rosbag/leg_tracker_positive_1.bag",
        ["--reference", "static", "--scan-topic", "right_scan"],
        "static",
    ),
]
#: Share of a recording (its first pairs in time) the "adapted" figures calibrate on.
ADAPT_SHARE = 0.3
ODOMETRY_COLUMNS = ("odom_trans_z", "odom_rot_z", "has_odometry", "odom_max_z")


def _run(cmd: Sequence[str]) -> None:
    log.info("$ %s", shlex.join(cmd))
    subprocess.run(list(cmd), check=True)


def _scanguard() -> str:
    exe = Path(sys.executable).with_name("scanguard")
    return str(exe) if exe.exists() else "scanguard"


# ------------------------------------------------------------------------------------------
# 1-2: data and models (resumable: builds resume, trainings are skipped when model.pt exists)
# ------------------------------------------------------------------------------------------


def build_data(matcher: str, data: Path, config: Path, workers: int) -> dict[str, Path]:
    sim = data / "sim"
    cmd = [_scanguard(), "dataset", "build", "-c", str(config), "-o", str(sim)]
    _run([*cmd, "-j", str(workers), "--matcher", matcher])
    out = {"sim": sim}
    groups: dict[str, list[tuple[str, list[str]]]] = {}
    for rel, extra, folder in RECORDINGS:
        if (SHARED / rel).exists():
            groups.setdefault(folder, []).append((rel, extra))
        else:
            log.warning("%s: not found; the real-data figures leave it out", SHARED / rel)
    for folder, items in groups.items():
        cmd = [_scanguard(), "dataset", "build", "-c", str(config), "-o", str(data / folder)]
        cmd += ["--matcher", matcher]
        for rel, _extra in items:
            cmd += ["-r", str(SHARED / rel)]
        cmd += items[0][1]  # one option set per folder (the static bag has its own)
        _run(cmd)
        out[folder] = data / folder
    return out


def train_model(
    sim: Path,
    config: Path,
    out: Path,
    exclude: Sequence[str] = (),
    real: Sequence[Path] = (),
) -> Path:
    """Train (unless ``out/model.pt`` exists) on the simulated train split minus ``exclude``.

    With ``real`` stores, their pairs (split ``heldout``) are training pairs too, except the
    recordings in ``exclude``.
    """
    model = out / "model.pt"
    if model.exists():
        log.info("%s exists; not retrained", model)
        return model
    cfg = TrainConfig.from_yaml(config)
    update: dict[str, Any] = {
        "exclude_environments": sorted({*cfg.exclude_environments, OFFICE, *exclude})
    }
    if real:
        update["train_split"] = sorted({*cfg.train_split, "heldout"})
    cfg = cfg.model_copy(update=update)
    out.parent.mkdir(parents=True, exist_ok=True)
    cfg_path = out.parent / f"{out.name}.yaml"
    atomic_write_text(cfg_path, cfg.to_yaml())
    t0 = time.perf_counter()
    data = [a for p in (sim, *real) for a in ("-d", str(p))]
    _run([_scanguard(), "train", *data, "-c", str(cfg_path), "-o", str(out)])
    log.info("trained %s in %.1f min", out, (time.perf_counter() - t0) / 60)
    return model


# ------------------------------------------------------------------------------------------
# 3: scores
# ------------------------------------------------------------------------------------------


class Pairs:
    """Labels, environments and per-method scores of a set of pairs (one store's subset)."""

    def __init__(self, store: PairStore, idx: np.ndarray) -> None:
        rec = store.records
        self.store, self.idx = store, idx
        self.labels = np.asarray(rec["label"], dtype=np.int64)[idx]
        self.env = np.asarray(rec["environment"]).astype(str)[idx]
        self.split = np.asarray(rec["split"]).astype(str)[idx]
        self.scores: dict[str, np.ndarray] = {}

    def where(self, mask: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        return self.labels[mask], {k: v[mask] for k, v in self.scores.items()}


def hide_odometry(feats: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = dict(feats)
    for k in ODOMETRY_COLUMNS:
        out[k] = np.zeros_like(out[k])
    return out


def cnn_logits(det: FaultDetector, pairs: Pairs, cache: Path, hidden: bool = False) -> np.ndarray:
    # a cache belongs to one model file and one set of pairs: a retrained model recomputes
    st = Path(det.source).stat()
    key = np.array([st.st_size, st.st_mtime_ns, len(pairs.idx)], dtype=np.int64)
    if cache.exists():
        with np.load(cache) as old:
            if "key" in old and np.array_equal(old["key"], key):
                return np.asarray(old["logits"])
    images = render_all(pairs.store, pairs.idx, det.style, progress=True)
    feats = store_features(pairs.store, pairs.idx, det.odometry_noise, det.reads_profile)
    if hidden:
        feats = hide_odometry(feats)
    z = det.predict_logits(images, features=feats if det.metric_names else None)
    cache.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(cache) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, logits=z, key=key)
    return z


def fit_classical(
    sim: PairStore, exclude: Sequence[str] = (), real: PairStore | None = None
) -> dict[str, Any]:
    """Every classical detector fitted on the pairs the CNN trains on (same ``exclude``)."""
    feats, y = _train_pairs(sim, exclude, "train")
    if real is not None:
        f_r, y_r = _train_pairs(real, exclude, None)
        feats = {k: np.concatenate([feats[k], f_r[k]]) for k in feats if k in f_r}
        y = np.concatenate([y, y_r])
    fitted = {}
    for name in [*BASELINES, *ODOMETRY_BASELINES]:
        fitted[name] = make_baseline(name).fit(feats, y)
    return fitted


def _train_pairs(
    store: PairStore, exclude: Sequence[str], split: str | None
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    idx = store.indices(split)
    env = np.asarray(store.records["environment"]).astype(str)[idx]
    idx = idx[~np.isin(env, [*exclude, OFFICE])]
    return store_features(store, idx), np.asarray(store.records["label"])[idx]


def classical_scores(
    fitted: dict[str, Any], pairs: Pairs, hidden: bool = False
) -> dict[str, np.ndarray]:
    feats = store_features(pairs.store, pairs.idx)
    if hidden:
        feats = hide_odometry(feats)
    return {name: det.predict_proba(feats) for name, det in fitted.items()}


# ------------------------------------------------------------------------------------------
# 4: held-out protocol and tables
# ------------------------------------------------------------------------------------------


def _pct(v: Any) -> str:
    return "-" if v is None or not math.isfinite(float(v)) else f"{100 * float(v):.1f}"


def _num(v: Any, d: int = 3) -> str:
    return "-" if v is None or not math.isfinite(float(v)) else f"{float(v):.{d}f}"


def _clean(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    if isinstance(v, float | np.floating):
        return None if not math.isfinite(float(v)) else float(v)
    if isinstance(v, np.integer):
        return int(v)
    return v


def heldout(
    ev: tuple[np.ndarray, dict[str, np.ndarray]], sel: tuple[np.ndarray, dict[str, np.ndarray]]
) -> dict[str, Any]:
    res = evaluate_heldout(ev[0], ev[1], sel[0], sel[1], calibrated=("cnn",))
    return {k: {**r.row, "proba": r.proba} for k, r in res.items()}


def concat(*parts: tuple[np.ndarray, dict[str, np.ndarray]]) -> tuple[np.ndarray, dict]:
    labels = np.concatenate([p[0] for p in parts])
    keys = parts[0][1].keys()
    return labels, {k: np.concatenate([p[1][k] for p in parts]) for k in keys}


def pooled_rows(per: list[dict[str, Any]], labels: list[np.ndarray]) -> dict[str, Any]:
    """Rows over the concatenation of several held-out sets (each with its own threshold)."""
    from scanguard.scoring import confusion, expected_calibration_error

    y = np.concatenate(labels)
    out = {}
    for name in per[0]:
        # a pair is flagged by its own set's threshold: compare proba - threshold with 0
        margin = np.concatenate([p[name]["proba"] - p[name]["threshold"] for p in per])
        row = dict(confusion(y, margin, 0.0))
        row["auc"] = math.nan  # margins of different sets do not rank jointly
        if name == "cnn":
            row["ece"] = expected_calibration_error(
                y, np.concatenate([p[name]["proba"] for p in per])
            )
        else:
            row["ece"] = math.nan
        row["proba"] = np.concatenate([p[name]["proba"] for p in per])
        out[name] = row
    return out


def comparison_table(title: str, rows: dict[str, dict[str, Any]]) -> list[str]:
    """One line per set: CNN accuracy / balanced accuracy / ECE against the best classical."""
    lines = [
        f"### {title}",
        "",
        "| set | n (fault) | CNN acc | CNN bal. acc | CNN recall | CNN F1 | CNN AUC | CNN ECE | "
        "best classical acc (method) | best classical bal. acc (method) | CNN at or above "
        "every classical (acc and bal. acc) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, res in rows.items():
        c = res["cnn"]
        others = {k: v for k, v in res.items() if k != "cnn"}
        best_acc = max(others, key=lambda k: _f(others[k]["accuracy"]))
        best_bal = max(others, key=lambda k: _f(others[k]["balanced_accuracy"]))
        wins = all(
            _f(c["accuracy"]) >= _f(o["accuracy"]) - 1e-12
            and (
                not math.isfinite(_f(o["balanced_accuracy"]))
                or _f(c["balanced_accuracy"]) >= _f(o["balanced_accuracy"]) - 1e-12
            )
            for o in others.values()
        )
        lines.append(
            f"| {name} | {c['n']} ({c['TP'] + c['FN']}) | {_pct(c['accuracy'])} | "
            f"{_num(c['balanced_accuracy'])} | {_pct(c['recall'])} | {_pct(c['f1'])} | "
            f"{_num(c['auc'])} | {_num(c['ece'])} | {_pct(others[best_acc]['accuracy'])} "
            f"({best_acc}) | {_num(others[best_bal]['balanced_accuracy'])} ({best_bal}) | "
            f"{'yes' if wins else '**no**'} |"
        )
    return [*lines, ""]


def method_table(title: str, rows: dict[str, dict[str, Any]], metric: str) -> list[str]:
    sets = list(rows)
    methods = list(next(iter(rows.values())))
    fmt = _pct if metric == "accuracy" else _num
    lines = [
        f"### {title}",
        "",
        "| method | " + " | ".join(sets) + " |",
        "|---|" + "---|" * len(sets),
    ]
    for m in methods:
        vals = []
        for s in sets:
            v = rows[s][m][metric]
            best = max(_f(rows[s][k][metric]) for k in methods)
            cell = fmt(v)
            vals.append(f"**{cell}**" if math.isfinite(_f(v)) and _f(v) >= best - 1e-12 else cell)
        lines.append(f"| {m} | " + " | ".join(vals) + " |")
    return [*lines, ""]


def _rel(p: Path) -> Path:
    return p.relative_to(ROOT) if p.is_relative_to(ROOT) else p


def _f(v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return -math.inf
    return x if math.isfinite(x) else -math.inf


def plot_roc(panels: list[tuple[str, np.ndarray, dict[str, np.ndarray]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.metrics import roc_curve

    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.4), squeeze=False)
    for ax, (title, y, scores) in zip(axes[0], panels, strict=True):
        keep = (y == 0) | (y == 1)
        for name, s in scores.items():
            if len(set(y[keep].tolist())) < 2:
                continue
            fpr, tpr, _ = roc_curve(y[keep], np.nan_to_num(s[keep], nan=np.inf, posinf=1e9))
            ax.plot(fpr, tpr, lw=2.0 if name == "cnn" else 1.0, label=name)
        ax.plot([0, 1], [0, 1], "k:", lw=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("false alarm rate (normal flagged)")
        ax.set_ylabel("fault recall")
        ax.legend(fontsize=7, loc="lower right")
        ax.grid(alpha=0.3)
    save_figure(fig, path, dpi=100)


# ------------------------------------------------------------------------------------------
# main
# ------------------------------------------------------------------------------------------


def score(
    det: FaultDetector, fitted: dict[str, Any], pairs: Pairs, cache: Path, hidden: bool = False
) -> Pairs:
    """Fill ``pairs.scores``: the CNN's logits and every classical detector's score."""
    pairs.scores = {"cnn": cnn_logits(det, pairs, cache, hidden)}
    pairs.scores.update(classical_scores(fitted, pairs, hidden=hidden))
    return pairs


def everything(pairs: Pairs) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    return pairs.where(np.ones(len(pairs.idx), bool))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--matcher", default="icp-paper")
    ap.add_argument("--data", type=Path, default=None, help="default: data/card/<matcher>")
    ap.add_argument("--work", type=Path, default=None, help="default: runs/card/<matcher>")
    ap.add_argument("--out", type=Path, default=None, help="default: docs/model_card/<matcher>")
    ap.add_argument("--dataset-config", type=Path, default=ROOT / "configs" / "transfer.yaml")
    ap.add_argument("--train-config", type=Path, default=ROOT / "configs" / "train_transfer.yaml")
    ap.add_argument(
        "--real-in-training",
        action="store_true",
        help="train on the real recordings too: one model per left-out recording r, trained "
        "without r and without the selection recording s (the next one), thresholds on office + s",
    )
    ap.add_argument(
        "--calibration-recording",
        default="freiburg-079-corrected",
        help="with --real-in-training: the recording the shipped model is calibrated on "
        "(with the office) and not trained on",
    )
    ap.add_argument("--loeo", action="store_true", help="also train 4 leave-one-env-out models")
    ap.add_argument("--ship", action="store_true", help="write the model into the package")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    configure_logging()
    m = args.matcher
    data = args.data or ROOT / "data" / "card" / m
    work = args.work or ROOT / "runs" / "card" / m
    out = args.out or ROOT / "docs" / "model_card" / m
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    scores_dir = work / "scores"

    stores = build_data(m, data, args.dataset_config, args.workers)
    sim = PairStore.open(stores["sim"])
    real_dirs = [stores[k] for k in ("real", "static") if k in stores]
    real = PairStore.open(real_dirs) if real_dirs else None
    recordings = (
        list(dict.fromkeys(np.asarray(real.records["environment"]).astype(str).tolist()))
        if real is not None
        else []
    )
    with_real = bool(args.real_in_training and real is not None)
    cal_rec = args.calibration_recording if with_real else None
    if cal_rec is not None and cal_rec not in recordings:
        raise SystemExit(f"--calibration-recording {cal_rec!r} is not one of {recordings}")

    # the main (shipped) model
    excl = [cal_rec] if cal_rec else []
    name = "model-real" if with_real else "model"
    model_path = train_model(
        stores["sim"], args.train_config, work / name, excl, real_dirs if with_real else ()
    )
    det = FaultDetector.load(model_path, calibrated=False)
    fitted = fit_classical(sim, excl, real if with_real else None)
    sim_idx = sim.indices(["test", "heldout"], include_ambiguous=True)
    simp = score(det, fitted, Pairs(sim, sim_idx), scores_dir / f"{name}-sim.npz")
    hidden = score(
        det, fitted, Pairs(sim, sim_idx), scores_dir / f"{name}-sim-hidden.npz", hidden=True
    )
    realp = None
    if real is not None:
        realp = score(
            det,
            fitted,
            Pairs(real, real.indices(None, include_ambiguous=True)),
            scores_dir / f"{name}-real.npz",
        )
    office = simp.where(simp.env == OFFICE)
    office_hidden = hidden.where(hidden.env == OFFICE)
    if realp is None:
        real_sel = None
    elif cal_rec is not None:
        real_sel = realp.where(realp.env == cal_rec)
    else:
        real_sel = everything(realp)
    sel_sim = concat(office, real_sel) if real_sel is not None else office

    results: dict[str, Any] = {}
    sim_rows: dict[str, Any] = {}
    for e in [e for e in dict.fromkeys(simp.env.tolist()) if e != OFFICE]:
        mask = (simp.env == e) & (simp.split == "test")
        label = f"{PAPER_ENVS.get(e, '')} {e}".strip()
        sim_rows[label] = heldout(simp.where(mask), sel_sim)
        if e == "corridor":
            sel_h = concat(office_hidden, real_sel) if real_sel is not None else office_hidden
            sim_rows[f"{label}, odometry hidden"] = heldout(hidden.where(mask), sel_h)
    if real_sel is not None:
        sim_rows["E5 office (held out)"] = heldout(office, real_sel)
    results["sim"] = sim_rows

    real_rows: dict[str, Any] = {}
    adapted_rows: dict[str, Any] = {}
    folds: dict[str, str] = {}
    if realp is not None and real is not None:
        per, labs, per_a, labs_a = [], [], [], []
        for k, r in enumerate(recordings):
            ev_mask = realp.env == r
            if with_real:
                s_rec = recordings[(k + 1) % len(recordings)]
                folds[r] = s_rec
                mp = train_model(
                    stores["sim"], args.train_config, work / f"loro-{r}", [r, s_rec], real_dirs
                )
                d = FaultDetector.load(mp, calibrated=False)
                f_k = fit_classical(sim, [r, s_rec], real)
                fold_real = score(d, f_k, Pairs(real, realp.idx), scores_dir / f"loro-{r}-real.npz")
                off = score(
                    d,
                    f_k,
                    Pairs(sim, sim.indices("heldout", environment=OFFICE, include_ambiguous=True)),
                    scores_dir / f"loro-{r}-office.npz",
                )
                ev = fold_real.where(ev_mask)
                sel = concat(everything(off), fold_real.where(fold_real.env == s_rec))
            else:
                ev = realp.where(ev_mask)
                sel = concat(office, realp.where(~ev_mask))
            real_rows[r] = heldout(ev, sel)
            per.append(real_rows[r])
            labs.append(ev[0])
            # what `scanguard calibrate` does for a user: recalibrate on the first 30 % of the
            # recording (in time), judge the remaining 70 %
            cut = round(ADAPT_SHARE * len(ev[0]))
            first = (ev[0][:cut], {k: v[:cut] for k, v in ev[1].items()})
            rest = (ev[0][cut:], {k: v[cut:] for k, v in ev[1].items()})
            adapted_rows[r] = heldout(rest, first)
            per_a.append(adapted_rows[r])
            labs_a.append(rest[0])
        real_rows["all recordings (each left out in turn)"] = pooled_rows(per, labs)
        adapted_rows["all recordings"] = pooled_rows(per_a, labs_a)
    results["real"] = real_rows
    results["adapted"] = adapted_rows

    loeo_rows: dict[str, Any] = {}
    if args.loeo:
        for e, code in PAPER_ENVS.items():
            ex = [e, f"{e}_dr"]
            mp = train_model(stores["sim"], args.train_config, work / f"loeo-{e}", ex)
            d = FaultDetector.load(mp, calibrated=False)
            f_e = fit_classical(sim, ex)
            ev_p = score(
                d,
                f_e,
                Pairs(sim, sim.indices(None, environment=e, include_ambiguous=True)),
                scores_dir / f"loeo-{e}-eval.npz",
            )
            off = score(
                d,
                f_e,
                Pairs(sim, sim.indices("heldout", environment=OFFICE, include_ambiguous=True)),
                scores_dir / f"loeo-{e}-office.npz",
            )
            sel = everything(off)
            if real is not None and realp is not None:
                rp = score(d, f_e, Pairs(real, realp.idx), scores_dir / f"loeo-{e}-real.npz")
                sel = concat(sel, everything(rp))
            loeo_rows[f"{code} {e} (all 12 sequences; trained without {e}, {e}_dr)"] = heldout(
                everything(ev_p), sel
            )
    results["loeo"] = loeo_rows

    write_outputs(
        out, args, m, model_path, det, stores, recordings, results, folds, cal_rec, t_start
    )
    plot_figures(out, m, simp, office, realp, recordings, sim_rows, real_rows)
    if args.ship:
        ship(m, model_path, sel_sim, fitted, sim, simp, realp, cal_rec)
    log.info("model card for %s written to %s", m, out)
    return 0


def write_outputs(
    out: Path,
    args: argparse.Namespace,
    m: str,
    model_path: Path,
    det: FaultDetector,
    stores: dict[str, Path],
    recordings: list[str],
    results: dict[str, Any],
    folds: dict[str, str],
    cal_rec: str | None,
    t_start: float,
) -> None:
    info = det.checkpoint.get("info", {})
    cmd = shlex.join(["python", *sys.argv])
    trained_on = f"the train split of `{stores['sim'].name}`"
    if cal_rec is not None:
        trained_on += f" and every real recording except `{cal_rec}`"
    lines = [
        f"# Model card tables: matcher `{m}`",
        "",
        f"Generated by `{cmd}` ({time.strftime('%Y-%m-%d %H:%M')}, "
        f"{(time.perf_counter() - t_start) / 60:.1f} min including any training).",
        "",
        f"- Model: `{_rel(model_path)}` (`{args.train_config.name}`, preset "
        f"`{det.model.config.preset}`), trained on {trained_on} ({info.get('n_train', '?')} "
        f"pairs, best epoch {info.get('best_epoch', '?')} of {info.get('epochs_run', '?')}).",
        f"- Data: `{args.dataset_config.name}` built with matcher `{m}`; real recordings: "
        + (", ".join(recordings) or "none")
        + ". Labels from the reference poses (`LabelConfig` thresholds; ambiguous pairs "
        "are in no figure).",
        "- Odometry input: the simulated sequences carry the simulator's drifting wheel "
        "odometry; the real recordings have none (CARMEN corrected logs expose none, the static "
        "bag has none), so their odometry input is masked.",
        "- Every threshold (and the CNN's Platt calibration) is chosen on selection pairs that "
        "are neither training data nor the pairs of the figure, by one rule for every method "
        "(max balanced accuracy; `scanguard.detect.protocol`). Classical detectors ("
        + ", ".join(f"`{n}`" for n in [*BASELINES, *ODOMETRY_BASELINES])
        + ") are fitted on the same pairs as the CNN.",
    ]
    if cal_rec is not None:
        lines.append(
            f"- Selection pairs: the office + `{cal_rec}` for the simulated figures (the "
            f"office figure: `{cal_rec}` only); real recording r: a model trained without r "
            "and without s, thresholds on the office + s, with (r -> s): "
            + ", ".join(f"{r} -> {s}" for r, s in folds.items())
            + "."
        )
    else:
        lines.append(
            "- Selection pairs: the office + every real recording for the simulated figures "
            "(the office figure: the real recordings only); real recording r: the office + the "
            "other recordings. The model never saw a real pair."
        )
    lines.append("")
    for key, title in (
        ("sim", "Simulation: test split of each environment (office: every pair, held out)"),
        ("real", "Real recordings, leave one recording out"),
        (
            "adapted",
            "Real recordings adapted as `scanguard calibrate` does: calibrated on the first "
            "30 % of the recording, judged on the other 70 %",
        ),
        ("loeo", "Leave one environment out"),
    ):
        if results[key]:
            lines += comparison_table(title, results[key])
            lines += method_table(f"{title}: accuracy (%)", results[key], "accuracy")
            lines += method_table(f"{title}: balanced accuracy", results[key], "balanced_accuracy")
    atomic_write_text(out / "tables.md", "\n".join(lines))
    dump = {
        "command": cmd,
        "matcher": m,
        "model": str(_rel(model_path)),
        "folds": folds,
        "results": _clean(
            {
                k: {
                    s: {n: {kk: vv for kk, vv in r.items() if kk != "proba"} for n, r in v.items()}
                    for s, v in rows.items()
                }
                for k, rows in results.items()
            }
        ),
    }
    atomic_write_text(out / "results.json", json.dumps(dump, indent=1))


def plot_figures(
    out: Path,
    m: str,
    simp: Pairs,
    office: tuple[np.ndarray, dict[str, np.ndarray]],
    realp: Pairs | None,
    recordings: list[str],
    sim_rows: dict[str, Any],
    real_rows: dict[str, Any],
) -> None:
    panels = [
        ("simulation, test split", *simp.where(simp.split == "test")),
        ("office (held out)", *office),
    ]
    if realp is not None:
        panels.append(("real recordings (main model)", *everything(realp)))
    plot_roc(panels, out / "roc.png")
    rel = []
    if "E5 office (held out)" in sim_rows:
        rel.append(
            ("office (held out)", office[0], sim_rows["E5 office (held out)"]["cnn"]["proba"])
        )
    pooled = real_rows.get("all recordings (each left out in turn)")
    if pooled is not None and realp is not None:
        y = np.concatenate([realp.where(realp.env == r)[0] for r in recordings])
        rel.append(("real, leave one out", y, pooled["cnn"]["proba"]))
    if rel:
        plot_reliability(rel, out / "reliability.png", title=f"CNN ({m}), held-out calibration")


def ship(
    matcher: str,
    model_path: Path,
    sel: tuple[np.ndarray, dict[str, np.ndarray]],
    fitted: dict[str, Any],
    sim: PairStore,
    simp: Pairs,
    realp: Pairs | None,
    cal_rec: str | None,
) -> None:
    """Calibrate on the selection pairs and write the model and the best classical detector."""
    pkg = ROOT / "src" / "scanguard" / "models"
    where = "office (E5) + " + (f"`{cal_rec}`" if cal_rec else "every shared real recording")
    fit = fit_calibration(sel[0], sel[1]["cnn"], method="platt", fitted_on=where)
    name = "default.pt" if matcher == "icp-paper" else f"{matcher}.pt"
    save_calibrated(model_path, fit.calibration, pkg / name)
    log.info("shipped %s (threshold %.3f)", pkg / name, fit.calibration.threshold)
    # the best classical detector on the same selection pairs, threshold by the same rule
    f_sel = store_features(sim, simp.idx[simp.env == OFFICE])
    if realp is not None:
        mask = np.ones(len(realp.idx), bool) if cal_rec is None else realp.env == cal_rec
        f_r = store_features(realp.store, realp.idx[mask])
        f_sel = {k: np.concatenate([f_sel[k], f_r[k]]) for k in f_sel if k in f_r}
    # rank by the mean balanced accuracy over domains (the selection pairs' office and real
    # recordings, and each simulated environment's val split), not over the pooled selection
    # pairs: a single-feature threshold that suits the selection domains can flag everything
    # elsewhere (the overlap test chosen on the office + FR079 flagged every pair of the demo)
    val = sim.indices("val")
    f_val = store_features(sim, val)
    y_val = np.asarray(sim.records["label"])[val]
    env_val = np.asarray(sim.records["environment"]).astype(str)[val]
    env_sel = [np.full(int(np.sum(simp.env == OFFICE)), OFFICE)]
    if realp is not None:
        env_sel.append(realp.env if cal_rec is None else realp.env[realp.env == cal_rec])
    domains = np.concatenate(env_sel)
    best, best_bal = None, -1.0
    for bname, det in fitted.items():
        if bname in ODOMETRY_BASELINES:
            continue  # run's baseline instance reads no odometry
        det.select_threshold(f_sel, sel[0])
        per = _per_domain_balanced(det.predict(f_sel), sel[0], domains)
        per += _per_domain_balanced(det.predict(f_val), y_val, env_val)
        bal = float(np.mean(per)) if per else -1.0
        log.info("classical %s: mean per-domain balanced accuracy %.3f", bname, bal)
        if bal > best_bal:
            best, best_bal = det, bal
    assert best is not None
    bpath = pkg / ("baseline.json" if matcher == "icp-paper" else f"baseline-{matcher}.json")
    save_detector(best, bpath)
    kind = "metrics model" if isinstance(best, MetricsModelDetector) else "threshold"
    log.info(
        "shipped classical %s (%s, mean per-domain bal. acc %.3f): %s",
        best.name,
        kind,
        best_bal,
        bpath,
    )


def _per_domain_balanced(pred: np.ndarray, y: np.ndarray, domain: np.ndarray) -> list[float]:
    out = []
    for d in dict.fromkeys(domain.tolist()):
        m = (domain == d) & (y >= 0)
        yy, pp = y[m], pred[m]
        if (yy == 1).any() and (yy == 0).any():
            out.append(0.5 * (float(np.mean(pp[yy == 1] == 1)) + float(np.mean(pp[yy == 0] == 0))))
    return out


if __name__ == "__main__":
    sys.exit(main())
