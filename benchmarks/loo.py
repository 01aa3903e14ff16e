"""Leave-one-environment-out evaluation of a training recipe on the simulated E1-4 environments.

For each held-out environment E (lobby, corridor, glass, hall): train the recipe (default: the
shipped ``configs/train.yaml``, preset ``cnn+metrics``) on a seeded subset of the *train* split
of the other three environments, pick the best epoch and the operating threshold on *their* val
split (`scanguard.detect.train.train_images`), and score every labelled pair of E, all splits
(`scanguard.scoring.confusion`). The office (E5) is never used.

Everything is rendered once (`scanguard.detect.train.load_store_images`); the train time per fold is
the `train_images` call only (rendering is reported separately).

    python benchmarks/loo.py [--data data/paper] [--config configs/train.yaml]
        [--max-train 4000] [--epochs 3] [--threads 2] [--out /tmp/loo]

Writes ``loo.md`` (markdown table), ``loo.json`` (rows + budget + command) and ``config.yaml``
(the resolved training config) to ``--out`` and prints a rich table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

# idle OpenMP workers must sleep, not spin, on a shared machine (set before torch loads)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from scanguard.config import save_config
from scanguard.dataset import PairStore
from scanguard.detect.train import load_store_images, train_images
from scanguard.detect.train_config import TrainConfig
from scanguard.detect.train_epoch import predict_proba
from scanguard.fsutil import atomic_write_text
from scanguard.scoring import confusion

ENVIRONMENTS = {"lobby": "E1", "corridor": "E2", "glass": "E3", "hall": "E4"}
ROOT = Path(__file__).resolve().parents[1]


def _pct(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{100 * v:.1f}%"


def _auc(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.3f}"


HEADER = (
    "held-out env",
    "n",
    "TP",
    "FN",
    "FP",
    "TN",
    "recall",
    "precision",
    "accuracy",
    "ROC AUC",
    "threshold",
    "train time",
)


def _cells(r: dict[str, Any]) -> list[str]:
    return [
        f"{ENVIRONMENTS.get(r['environment'], '')} {r['environment']}".strip(),
        str(r["n"]),
        str(r["TP"]),
        str(r["FN"]),
        str(r["FP"]),
        str(r["TN"]),
        _pct(r["recall"]),
        _pct(r["precision"]),
        _pct(r["accuracy"]),
        _auc(r["auc"]),
        f"{r['threshold']:.3f}",
        f"{r['train_s']:.0f} s",
    ]


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The rows as a GitHub markdown table."""
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(_cells(r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "paper"), help="pair store")
    ap.add_argument("--config", default=str(ROOT / "configs" / "train.yaml"), help="recipe")
    ap.add_argument("--max-train", type=int, default=4000, help="seeded training subset size")
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--seed", type=int, default=None, help="override the recipe's seed")
    ap.add_argument(
        "--environments", nargs="+", default=list(ENVIRONMENTS), help="folds (held-out envs)"
    )
    ap.add_argument("--out", default="/tmp/loo")
    args = ap.parse_args()

    # piped output (logs) would squeeze the 12 columns into 80 characters
    console = Console(width=None if sys.stdout.isatty() else 160)
    torch.set_num_threads(args.threads)
    update: dict[str, Any] = {
        "epochs": args.epochs,
        "max_train": args.max_train,
        "threads": args.threads,
    }
    if args.seed is not None:
        update["seed"] = args.seed
    cfg = TrainConfig.from_yaml(args.config).model_copy(update=update).resolved()
    assert cfg.model is not None and cfg.style is not None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out)

    store = PairStore.open(args.data)
    envs = list(ENVIRONMENTS)
    t0 = time.perf_counter()
    data, label_rule = load_store_images(
        store, cfg.style, environments=envs, metrics=list(cfg.model.metrics) or None
    )
    render_s = time.perf_counter() - t0
    split = np.asarray(store.records["split"]).astype(str)[data.index]
    console.print(
        f"rendered {len(data)} labelled pairs of {', '.join(envs)} in {render_s:.0f} s "
        f"({cfg.preset}, {cfg.style['kind']} {cfg.style['size']}px)"
    )

    rows: list[dict[str, Any]] = []
    for k, env in enumerate(args.environments, 1):
        others = data.environment != env
        train = data.subset(others & (split == "train"))
        val = data.subset(others & (split == "val"))
        test = data.subset(data.environment == env)
        console.print(
            f"[{k}/{len(args.environments)}] held out {env}: train on "
            f"{min(len(train), args.max_train)} of {len(train)} pairs, val {len(val)}, "
            f"test {len(test)}"
        )
        t1 = time.perf_counter()
        res = train_images(
            cfg,
            train,
            val,
            label_thresholds=label_rule,
            data_info={"held_out": env},
        )
        train_s = time.perf_counter() - t1
        thr = float(res.checkpoint["threshold"])
        proba = predict_proba(
            res.model, test.images, channels_last=cfg.channels_last, metrics=test.metrics
        )
        row: dict[str, Any] = {"environment": env, **confusion(test.labels, proba, thr)}
        info = res.checkpoint["info"]
        row.update(
            train_s=train_s,
            n_train=int(info["n_train"]),
            n_val=int(info["n_val"]),
            best_epoch=int(info["best_epoch"]),
            val_accuracy=float(info.get("val_accuracy_at_threshold", math.nan)),
        )
        rows.append(row)
        console.print(
            f"    accuracy {_pct(row['accuracy'])}, AUC {_auc(row['auc'])}, "
            f"threshold {thr:.3f}, best epoch {row['best_epoch']}, {train_s:.0f} s"
        )

    table = Table(
        title=f"Leave-one-environment-out, {cfg.preset}: {args.max_train} train pairs, "
        f"{args.epochs} epochs, {args.threads} threads"
    )
    for h in HEADER:
        table.add_column(h, justify="left" if h == "held-out env" else "right")
    for r in rows:
        table.add_row(*_cells(r))
    console.print(table)

    command = "python benchmarks/loo.py " + shlex.join(sys.argv[1:])
    budget = {
        "preset": cfg.preset,
        "config": str(args.config),
        "max_train": args.max_train,
        "epochs": args.epochs,
        "threads": args.threads,
        "seed": cfg.seed,
        "render_s": render_s,
        "total_train_s": sum(r["train_s"] for r in rows),
    }
    atomic_write_text(out / "loo.md", f"`{command.strip()}`\n\n" + markdown_table(rows))

    def clean(v: Any) -> Any:
        return None if isinstance(v, float) and not math.isfinite(v) else v

    payload = {
        "positive_class": "fault",
        "command": command.strip(),
        "budget": budget,
        "rows": [{k: clean(v) for k, v in r.items()} for r in rows],
    }
    atomic_write_text(out / "loo.json", json.dumps(payload, indent=2))
    console.print(f"wrote {out / 'loo.md'}, {out / 'loo.json'}, {out / 'config.yaml'}")


if __name__ == "__main__":
    main()
