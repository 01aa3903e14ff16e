"""One training epoch, validation, and the helpers around them.

The epoch order, the learning-rate schedule, the odometry dropout and the divergence checks.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch
import torch.nn.functional as nnf
from numpy.typing import NDArray
from tqdm.auto import tqdm

from scanguard.detect.distributed import dist_rank_world
from scanguard.detect.model import FaultCNN, images_to_tensor
from scanguard.detect.train_config import ImageSet, TrainConfig
from scanguard.errors import ConfigError
from scanguard.pairs.odometry import ODOMETRY_FEATURES


def _augment(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    # one random symmetry of the square per batch keeps it cheap; batches differ
    k = int(torch.randint(0, 4, (1,), generator=gen))
    if k:
        x = torch.rot90(x, k, dims=(2, 3))
    if int(torch.randint(0, 2, (1,), generator=gen)):
        x = torch.flip(x, dims=(3,))
    return x


def predict_proba(
    model: FaultCNN,
    images: NDArray[np.uint8],
    batch_size: int = 256,
    channels_last: bool = True,
    metrics: NDArray[np.float32] | None = None,
) -> NDArray[np.float64]:
    """Fault probabilities ``(N,)`` of uint8 images ``(N, H, W, C)`` (eval mode, no grad).

    ``metrics`` ``(N, K)`` are the metric inputs of a hybrid model (ignored otherwise).
    """
    model.eval()
    out = np.empty(len(images), dtype=np.float64)
    use_m = model.uses_metrics
    if use_m and metrics is None:
        raise ConfigError(f"model {model.config.preset!r} needs ICP metrics next to the images")
    with torch.inference_mode():
        for s in range(0, len(images), batch_size):
            x = images_to_tensor(images[s : s + batch_size], channels_last)
            m = (
                torch.from_numpy(metrics[s : s + batch_size])
                if use_m and metrics is not None
                else None
            )
            out[s : s + batch_size] = torch.softmax(model(x, m), dim=1)[:, 1].double().numpy()
    return out


def epoch_order(
    labels: NDArray[np.int64], balanced: bool, gen: torch.Generator
) -> NDArray[np.int64]:
    """Indices of one epoch's training images (``len(labels)`` of them).

    A seeded permutation, or with ``balanced`` a class-balanced draw with replacement (each
    class gets half of the draws on average).
    """
    n = len(labels)
    if balanced and 0 < int(labels.sum()) < n:
        counts = np.bincount(labels, minlength=2).astype(np.float64)
        w = torch.from_numpy(0.5 / counts[labels])
        return torch.multinomial(w, n, replacement=True, generator=gen).numpy()
    return torch.randperm(n, generator=gen).numpy()


class DivergedError(Exception):
    """The training loss became NaN or infinite (carries the batch's loss)."""

    def __init__(self, loss: float) -> None:
        super().__init__(loss)
        self.loss = loss


def non_finite_weights(model: torch.nn.Module) -> list[str]:
    """Names of the parameters and float buffers that hold NaN or infinite values."""
    return [
        name
        for name, t in model.state_dict().items()
        if t.is_floating_point() and not bool(torch.isfinite(t).all())
    ]


def run_epoch(
    model: FaultCNN,
    data: ImageSet,
    cfg: TrainConfig,
    opt: torch.optim.Optimizer,
    gen: torch.Generator,
    desc: str,
    sched: torch.optim.lr_scheduler.LRScheduler | None = None,
) -> tuple[float, float, float]:
    """Train one epoch; returns (mean loss, accuracy, images per second) over all ranks.

    Raises:
        DivergedError: A batch's loss is NaN or infinite.
    """
    model.train()
    n = len(data)
    rank, world = dist_rank_world()
    # every rank draws the same order and augmentation: they share the seed and the draws
    order = epoch_order(data.labels, cfg.balanced, gen)
    labels = torch.from_numpy(data.labels)
    odo_cols = odometry_columns(model, cfg) if data.metrics is not None else None
    loss_sum, correct = 0.0, 0
    t0 = time.perf_counter()
    with tqdm(
        total=n, desc=desc, unit="img", leave=False, disable=None if rank == 0 else True
    ) as bar:
        for s in range(0, n, cfg.batch_size):
            batch = np.sort(order[s : s + cfg.batch_size])
            idx = batch[rank::world]  # this rank's share of the global batch
            x = images_to_tensor(data.images[idx], cfg.channels_last)
            y = labels[idx]
            m = torch.from_numpy(data.metrics[idx]) if data.metrics is not None else None
            if m is not None and odo_cols is not None:
                # hide the odometry of a share of the batch: 0 is "no odometry" after the
                # log1p transform, and the mask column says so
                hide = torch.rand(len(idx), generator=gen) < cfg.odometry_dropout
                m[hide] = m[hide].index_fill(1, odo_cols, 0.0)
            if cfg.augment:
                x = _augment(x, gen)
                if cfg.channels_last:
                    x = x.contiguous(memory_format=torch.channels_last)
            opt.zero_grad(set_to_none=True)
            logits = model(x, m)
            if world == 1:
                loss = nnf.cross_entropy(logits, y, label_smoothing=cfg.label_smoothing)
                batch_loss = float(loss.detach())
                part = batch_loss * len(idx)
            else:
                # DDP averages gradients over ranks: sum / global batch * world gives the
                # gradient of the global batch's mean loss, whatever the shares' sizes
                total = nnf.cross_entropy(
                    logits, y, label_smoothing=cfg.label_smoothing, reduction="sum"
                )
                loss = total * (world / len(batch))
                part = float(total.detach())
                batch_loss = part / max(len(idx), 1)
            loss.backward()
            opt.step()
            if sched is not None:
                sched.step()
            if not math.isfinite(batch_loss):
                raise DivergedError(batch_loss)
            loss_sum += part
            correct += int((logits.argmax(1) == y).sum())
            bar.update(len(batch))
    if world > 1:
        sums = torch.tensor([loss_sum, float(correct)], dtype=torch.float64)
        torch.distributed.all_reduce(sums)
        loss_sum, correct = float(sums[0]), int(sums[1])
    dt = time.perf_counter() - t0
    return loss_sum / max(n, 1), correct / max(n, 1), n / max(dt, 1e-9)


def odometry_columns(model: Any, cfg: TrainConfig) -> torch.Tensor | None:
    """Metric columns of the odometry input (None: the model does not read it, or no dropout)."""
    names = list(getattr(model, "module", model).config.metrics)
    if "has_odometry" not in names or cfg.odometry_dropout <= 0.0:
        return None
    return torch.tensor([names.index(n) for n in ODOMETRY_FEATURES if n in names])


def with_hidden_odometry(
    metrics: NDArray[np.float32], model: Any, cfg: TrainConfig
) -> NDArray[np.float32]:
    """The training metrics as the network sees them: odometry hidden for a share of the pairs.

    The standardisation must be fitted on these: on data that always has odometry the mask
    column is constant, and a hidden pair would sit a million standard deviations away.
    """
    cols = odometry_columns(model, cfg)
    if cols is None:
        return metrics
    out = metrics.copy()
    hide = np.random.default_rng(cfg.seed).random(len(out)) < cfg.odometry_dropout
    out[np.ix_(hide, cols.numpy())] = 0.0
    return out


def make_schedule(
    opt: torch.optim.Optimizer, cfg: TrainConfig, steps_per_epoch: int
) -> torch.optim.lr_scheduler.LRScheduler | None:
    """Per-batch LR schedule over the whole ``epochs`` budget (early stopping cuts it short)."""
    total = max(cfg.epochs * steps_per_epoch, 1)
    if cfg.schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=total)
    if cfg.schedule == "onecycle":
        return torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=total)
    return None


def validate(
    model: FaultCNN, data: ImageSet, channels_last: bool
) -> tuple[float, float, NDArray[np.float64]]:
    """Log loss, accuracy at 0.5 and fault probabilities of ``data`` (eval mode)."""
    proba = predict_proba(model, data.images, channels_last=channels_last, metrics=data.metrics)
    y = data.labels
    eps = 1e-7
    p = np.clip(proba, eps, 1 - eps)
    loss = float(-np.mean(np.where(y == 1, np.log(p), np.log(1 - p)))) if len(y) else float("nan")
    acc = float(np.mean((proba >= 0.5) == (y == 1))) if len(y) else float("nan")
    return loss, acc, proba
