"""Inference latency / throughput and training speed of the fault-detection CNN presets.

Baseline: the paper preset (256x256x3, full widths), measured in the same run.

    python benchmarks/bench_model.py [--model PATH] [--repeats 200] [--train-batches 6]

Prints one table: per preset and backend, median single-pair latency (ms), batched throughput
(pairs/s, batch 64) and training speed (images/s, batch 16), each with its ratio against the
paper preset.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

# idle OpenMP workers must sleep, not spin, on a shared machine (set before torch loads)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from scanguard.detect.detector import FaultDetector
from scanguard.detect.model import build_model, get_preset, images_to_tensor
from scanguard.detect.train_config import default_style


def sparse_images(n: int, size: int, channels: int, seed: int = 0) -> np.ndarray:
    # scan images are mostly empty: ~3% of pixels set, like real renders
    rng = np.random.default_rng(seed)
    img = (rng.random((n, size, size, channels)) < 0.03).astype(np.uint8) * 255
    if channels == 3:  # paper style: white background
        img = 255 - img
    return img


def _feats(det: FaultDetector, n: int) -> np.ndarray | None:
    # hybrid presets also read the ICP metric vector (already transformed, standardised inside)
    return np.zeros((n, len(det.metric_names)), np.float32) if det.metric_names else None


def latency_ms(det: FaultDetector, img: np.ndarray, repeats: int) -> float:
    f = _feats(det, len(img))
    for _ in range(5):
        det.predict_images(img, features=f)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        det.predict_images(img, features=f)
        ts.append(time.perf_counter() - t0)
    return 1000 * statistics.median(ts)


def throughput(det: FaultDetector, imgs: np.ndarray, rounds: int = 3) -> float:
    f = _feats(det, len(imgs))
    det.predict_images(imgs[:8], features=None if f is None else f[:8])
    t0 = time.perf_counter()
    for _ in range(rounds):
        det.predict_images(imgs, batch_size=len(imgs), features=f)
    return rounds * len(imgs) / (time.perf_counter() - t0)


def train_speed(preset: str, batches: int, batch: int = 16) -> float:
    cfg = get_preset(preset)
    model = build_model(cfg).to(memory_format=torch.channels_last)
    model.train()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    imgs = sparse_images(batch, cfg.input_size, cfg.in_channels, seed=1)
    x = images_to_tensor(imgs)
    y = torch.arange(batch) % 2
    m = torch.zeros(batch, len(cfg.metrics)) if cfg.metrics else None
    for i in range(batches + 1):
        if i == 1:  # first step warms up the allocator / kernels
            t0 = time.perf_counter()
        opt.zero_grad()
        torch.nn.functional.cross_entropy(model(x, m), y).backward()
        opt.step()
    return batches * batch / (time.perf_counter() - t0)


def detector_for(preset: str) -> FaultDetector:
    cfg = get_preset(preset)
    torch.manual_seed(0)
    return FaultDetector(build_model(cfg), default_style(cfg))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--train-batches", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1, help="torch threads for inference")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    presets = [
        "paper",
        "compact128",
        "compact",
        "multiscale",
        "cnn+metrics",
        "cnn+metrics+odometry",
    ]
    for preset in presets:
        cfg = get_preset(preset)
        for backend in ("torch", "onnx"):
            det = detector_for(preset)
            if backend == "onnx":
                det = FaultDetector(det.model, det.style, backend="onnx", threads=args.threads)
            one = sparse_images(1, cfg.input_size, cfg.in_channels)
            many = sparse_images(64, cfg.input_size, cfg.in_channels)
            reps = max(10, args.repeats // 10) if preset == "paper" else args.repeats
            rows.append(
                {
                    "preset": preset,
                    "backend": backend,
                    "input": f"{cfg.input_size}x{cfg.input_size}x{cfg.in_channels}",
                    "lat": latency_ms(det, one, reps),
                    "thr": throughput(det, many, 1 if preset == "paper" else 3),
                }
            )
        torch.set_num_threads(2)
        tr = train_speed(preset, max(2, args.train_batches // 3 if preset == "paper" else 12))
        torch.set_num_threads(args.threads)
        for r in rows[-2:]:
            r["train"] = tr
    base = {r["backend"]: r for r in rows if r["preset"] == "paper"}
    t = Table(title=f"fault CNN inference ({args.threads} thread(s)) and training (2 threads)")
    for col in (
        "preset",
        "backend",
        "input",
        "median ms/pair",
        "x paper",
        "pairs/s (b=64)",
        "x paper",
        "train img/s (b=16)",
        "x paper",
    ):
        t.add_column(col, justify="right")
    for r in rows:
        b = base[r["backend"]]
        t.add_row(
            r["preset"],
            r["backend"],
            r["input"],
            f"{r['lat']:.3f}",
            f"{b['lat'] / r['lat']:.1f}",
            f"{r['thr']:.0f}",
            f"{r['thr'] / b['thr']:.1f}",
            f"{r['train']:.0f}",
            f"{r['train'] / b['train']:.1f}",
        )
    Console(width=150).print(t)


if __name__ == "__main__":
    main()
