"""Training of the fault-detection CNN: seeded, reproducible, with best-epoch selection.

Images are rendered once (uint8, ``(N, H, W, C)``) and kept in memory; each epoch visits the
training images in an order drawn from a seeded generator, so two runs with the same config
and data give the same weights (``torch.use_deterministic_algorithms`` is not forced because
some CPU kernels lack deterministic variants; on the CPU the results are bit-identical in
practice). The epoch with the best validation accuracy (ties: lower validation loss) is kept,
and training stops early after ``patience`` epochs without improvement.

Outputs (all written atomically into ``out_dir``): ``model.pt`` (checkpoint with config,
render style, label thresholds, operating threshold and weights), ``config.yaml`` (resolved
config), ``history.json`` and ``curves.png`` (loss / accuracy per epoch, paper Figure 10).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as nnf
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from tqdm.auto import tqdm

from scanguard.config import YamlModel, save_config
from scanguard.detect.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
from scanguard.detect.model import FaultCNN, ModelConfig, build_model, count_parameters, get_preset
from scanguard.errors import ConfigError, InputError
from scanguard.fsutil import atomic_path, atomic_write_text, save_figure
from scanguard.scoring import metric_threshold

log = logging.getLogger(__name__)


class TrainConfig(YamlModel):
    """Settings of one training run.

    Attributes:
        preset: Model preset (`scanguard.detect.model.PRESETS`), used when ``model`` is not given.
        model: Full architecture; filled from ``preset`` when resolving.
        style: Render style fields (`scanguard.detect.render.RenderStyle`); ``None`` derives it from
            the model (3 channels: ``paper`` kind, otherwise ``occupancy``; size = input size).
        epochs: Maximum number of epochs (paper: 17).
        batch_size: Mini-batch size (paper: 32).
        lr: Adam learning rate.
        weight_decay: Adam weight decay.
        patience: Stop after this many epochs without a better validation score (0: never).
        seed: Seed of weights, data order, dropout and augmentation.
        threads: ``torch.set_num_threads`` during training.
        augment: Random flips and 90-degree rotations of training images (a fault stays a
            fault under any rigid motion of the picture).
        channels_last: Use the channels-last memory format (faster convolutions on CPU).
        train_split: Split name(s) used for training.
        val_split: Split name(s) used for best-epoch selection.
        environments: Train/validate only on these environments (``None``: all).
        exclude_environments: Never train or validate on these (the held-out office).
        max_train: Use at most this many training pairs (seeded subset), e.g. for the slow
            paper preset.
        threshold_metric: How the operating threshold is chosen on the validation split:
            ``accuracy`` (maximise accuracy), ``f1`` or ``fixed`` (0.5).
        schedule: Learning-rate schedule over the ``epochs`` budget: ``constant``, ``cosine``
            (per-batch cosine decay to 0) or ``onecycle`` (`torch.optim.lr_scheduler.OneCycleLR`
            with ``lr`` as the peak).
        label_smoothing: Cross-entropy label smoothing.
        balanced: Draw each epoch's training order with class-balanced sampling (with
            replacement, same number of images per epoch) instead of a plain permutation.
        allow_incomplete: Train on a store whose build is unfinished (its manifest says
            ``complete: false``); refused by default.
        odometry_dropout: For a model that reads the odometry disagreement
            (`scanguard.pairs.odometry`): the share of training pairs, drawn anew every
            epoch, whose odometry is hidden (features 0, mask 0), so that one model serves
            recordings with and without odometry.
    """

    preset: str = "compact"
    model: ModelConfig | None = None
    style: dict[str, Any] | None = None
    epochs: int = Field(default=17, ge=1)
    batch_size: int = Field(default=16, ge=1)
    lr: float = Field(default=1e-3, gt=0)
    weight_decay: float = Field(default=0.0, ge=0)
    patience: int = Field(default=5, ge=0)
    seed: int = 0
    threads: int = Field(default=2, ge=1)
    augment: bool = True
    channels_last: bool = True
    train_split: list[str] = Field(default_factory=lambda: ["train"])
    val_split: list[str] = Field(default_factory=lambda: ["val"])
    environments: list[str] | None = None
    exclude_environments: list[str] = Field(default_factory=lambda: ["office"])
    max_train: int | None = Field(default=None, ge=1)
    threshold_metric: str = Field(default="accuracy", pattern="^(accuracy|f1|fixed)$")
    schedule: str = Field(default="constant", pattern="^(constant|cosine|onecycle)$")
    label_smoothing: float = Field(default=0.0, ge=0.0, lt=0.5)
    balanced: bool = False
    allow_incomplete: bool = False
    odometry_dropout: float = Field(default=0.3, ge=0.0, le=1.0)

    def resolved(self) -> TrainConfig:
        """A copy with ``model`` and ``style`` filled in."""
        model = self.model or get_preset(self.preset)
        model.check()
        style = dict(self.style) if self.style is not None else default_style(model)
        return self.model_copy(update={"model": model, "style": style}, deep=True)


def default_style(model: ModelConfig) -> dict[str, Any]:
    """Render style that matches a model's input (channels and size).

    3 channels: ``paper``; 2: ``occupancy``; 4 or 6: ``multiscale`` with one or two metric
    views (0.05 m/px, then 0.2 m/px).
    """
    c = model.in_channels
    if c in (4, 6):
        scales = [0.05, 0.2][: (c - 2) // 2]
        return {"kind": "multiscale", "size": model.input_size, "scales": scales}
    kind = "paper" if c == 3 else "occupancy"
    return {"kind": kind, "size": model.input_size}


@dataclass
class ImageSet:
    """Rendered pairs in memory.

    Attributes:
        images: uint8 ``(N, H, W, C)``.
        labels: int64 ``(N,)`` (0 normal, 1 fault, -1 ambiguous).
        environment: ``(N,)`` environment name per image.
        sequence: ``(N,)`` sequence name per image.
        index: ``(N,)`` record index in the source store (or running number).
        metrics: float32 ``(N, K)`` ICP metric inputs (`scanguard.detect.model.metric_inputs`) for
            hybrid models, else ``None``.
    """

    images: NDArray[np.uint8]
    labels: NDArray[np.int64]
    environment: NDArray[np.str_] = field(default_factory=lambda: np.array([], dtype=str))
    sequence: NDArray[np.str_] = field(default_factory=lambda: np.array([], dtype=str))
    index: NDArray[np.int64] = field(default_factory=lambda: np.array([], dtype=np.int64))
    metrics: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        n = len(self.images)
        if self.images.ndim != 4 or self.images.dtype != np.uint8:
            raise ConfigError(
                f"images must be uint8 (N, H, W, C), got {self.images.dtype} {self.images.shape}"
            )
        self.labels = np.asarray(self.labels, dtype=np.int64)
        if len(self.labels) != n:
            raise ConfigError(f"{n} images but {len(self.labels)} labels")
        if len(self.environment) != n:
            self.environment = np.full(n, "unknown")
        if len(self.sequence) != n:
            self.sequence = np.full(n, "unknown")
        if len(self.index) != n:
            self.index = np.arange(n, dtype=np.int64)
        if self.metrics is not None and len(self.metrics) != n:
            raise ConfigError(f"{n} images but {len(self.metrics)} metric rows")

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, mask: NDArray[np.bool_] | NDArray[np.int64]) -> ImageSet:
        """The images selected by a boolean mask or an index array."""
        return ImageSet(
            self.images[mask],
            self.labels[mask],
            self.environment[mask],
            self.sequence[mask],
            self.index[mask],
            None if self.metrics is None else self.metrics[mask],
        )


@dataclass
class TrainResult:
    """What a training run produced.

    Attributes:
        checkpoint: The checkpoint dict (as saved in ``model.pt``).
        model: The trained network (best epoch, eval mode).
        history: Per-epoch metrics.
        out_dir: Output folder, if one was written.
    """

    checkpoint: dict[str, Any]
    model: FaultCNN
    history: list[dict[str, float]]
    out_dir: Path | None = None


def images_to_tensor(images: NDArray[np.uint8], channels_last: bool = True) -> torch.Tensor:
    """uint8 ``(B, H, W, C)`` -> float32 ``(B, C, H, W)`` in ``[0, 1]``."""
    t = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)
    if channels_last:
        return t.contiguous(memory_format=torch.channels_last)
    return t.contiguous()


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


class _DivergedError(Exception):
    """The training loss became NaN or infinite (carries the batch's loss)."""

    def __init__(self, loss: float) -> None:
        super().__init__(loss)
        self.loss = loss


def _non_finite_weights(model: torch.nn.Module) -> list[str]:
    """Names of the parameters and float buffers that hold NaN or infinite values."""
    return [
        name
        for name, t in model.state_dict().items()
        if t.is_floating_point() and not bool(torch.isfinite(t).all())
    ]


def _run_epoch(
    model: FaultCNN,
    data: ImageSet,
    cfg: TrainConfig,
    opt: torch.optim.Optimizer,
    gen: torch.Generator,
    desc: str,
    sched: torch.optim.lr_scheduler.LRScheduler | None = None,
) -> tuple[float, float, float]:
    model.train()
    n = len(data)
    rank, world = dist_rank_world()
    # every rank draws the same order and augmentation: they share the seed and the draws
    order = epoch_order(data.labels, cfg.balanced, gen)
    labels = torch.from_numpy(data.labels)
    odo_cols = _odometry_columns(model, cfg) if data.metrics is not None else None
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
                raise _DivergedError(batch_loss)
            loss_sum += part
            correct += int((logits.argmax(1) == y).sum())
            bar.update(len(batch))
    if world > 1:
        sums = torch.tensor([loss_sum, float(correct)], dtype=torch.float64)
        torch.distributed.all_reduce(sums)
        loss_sum, correct = float(sums[0]), int(sums[1])
    dt = time.perf_counter() - t0
    return loss_sum / max(n, 1), correct / max(n, 1), n / max(dt, 1e-9)


def _odometry_columns(model: Any, cfg: TrainConfig) -> torch.Tensor | None:
    """Metric columns of the odometry input (None: the model does not read it, or no dropout)."""
    from scanguard.pairs.odometry import ODOMETRY_FEATURES

    names = list(getattr(model, "module", model).config.metrics)
    if "has_odometry" not in names or cfg.odometry_dropout <= 0.0:
        return None
    return torch.tensor([names.index(n) for n in ODOMETRY_FEATURES if n in names])


def _with_hidden_odometry(
    metrics: NDArray[np.float32], model: Any, cfg: TrainConfig
) -> NDArray[np.float32]:
    """The training metrics as the network sees them: odometry hidden for a share of the pairs.

    The standardisation must be fitted on these: on data that always has odometry the mask
    column is constant, and a hidden pair would sit a million standard deviations away.
    """
    cols = _odometry_columns(model, cfg)
    if cols is None:
        return metrics
    out = metrics.copy()
    hide = np.random.default_rng(cfg.seed).random(len(out)) < cfg.odometry_dropout
    out[np.ix_(hide, cols.numpy())] = 0.0
    return out


def dist_rank_world() -> tuple[int, int]:
    """This process's rank and the world size (``(0, 1)`` outside a process group)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def init_distributed() -> tuple[int, int]:
    """Join the process group that ``torchrun`` describes (``WORLD_SIZE`` > 1), once.

    The backend is ``nccl`` when CUDA is present, ``gloo`` otherwise. Outside ``torchrun``
    (no ``WORLD_SIZE``, or 1) nothing happens.

    Returns:
        This process's rank and the world size.

    Raises:
        ConfigError: torch was built without distributed support, or the group cannot be
            joined.
    """
    import os

    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1 or (dist.is_available() and dist.is_initialized()):
        return dist_rank_world()
    if not dist.is_available():
        raise ConfigError("WORLD_SIZE > 1 but this torch has no torch.distributed")
    backend = "nccl" if torch.cuda.is_available() else "gloo"
    try:
        dist.init_process_group(backend=backend)
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"cannot join the {backend} process group: {exc}") from None
    log.info("rank %d of %d (%s)", dist.get_rank(), dist.get_world_size(), backend)
    return dist_rank_world()


def _local_world() -> int:
    import os

    return max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))


def _broadcast_floats(values: Sequence[float]) -> list[float]:
    """Rank 0's ``values`` on every rank (as they are outside a process group)."""
    if dist_rank_world()[1] == 1:
        return list(values)
    t = torch.tensor(list(values), dtype=torch.float64)
    torch.distributed.broadcast(t, src=0)
    return [float(v) for v in t.tolist()]


def _make_schedule(
    opt: torch.optim.Optimizer, cfg: TrainConfig, steps_per_epoch: int
) -> torch.optim.lr_scheduler.LRScheduler | None:
    """Per-batch LR schedule over the whole ``epochs`` budget (early stopping cuts it short)."""
    total = max(cfg.epochs * steps_per_epoch, 1)
    if cfg.schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=total)
    if cfg.schedule == "onecycle":
        return torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=total)
    return None


def _evaluate(
    model: FaultCNN, data: ImageSet, channels_last: bool
) -> tuple[float, float, NDArray[np.float64]]:
    proba = predict_proba(model, data.images, channels_last=channels_last, metrics=data.metrics)
    y = data.labels
    eps = 1e-7
    p = np.clip(proba, eps, 1 - eps)
    loss = float(-np.mean(np.where(y == 1, np.log(p), np.log(1 - p)))) if len(y) else float("nan")
    acc = float(np.mean((proba >= 0.5) == (y == 1))) if len(y) else float("nan")
    return loss, acc, proba


def train_images(
    config: TrainConfig,
    train: ImageSet,
    val: ImageSet,
    out_dir: str | Path | None = None,
    *,
    label_thresholds: dict[str, Any] | None = None,
    data_info: dict[str, Any] | None = None,
    matchers: Sequence[str] | None = None,
) -> TrainResult:
    """Train on rendered images and keep the best validation epoch.

    Args:
        config: Training settings (resolved here if needed).
        train: Training images; ambiguous labels (-1) are dropped.
        val: Validation images (by sequence, disjoint from ``train``); may be empty, in which
            case the last epoch is kept and the threshold is 0.5.
        out_dir: Folder for ``model.pt``, ``config.yaml``, ``history.json``, ``curves.png``;
            ``None`` writes nothing.
        label_thresholds: The dataset's labelling rule, stored in the checkpoint.
        data_info: Free-form description of the data (stored in the checkpoint).
        matchers: Names of the matchers whose matches the images show, stored in the
            checkpoint (`FaultDetector.check_matcher`); ``None`` stores none (the detector
            then assumes ``icp-paper``, as for older checkpoints).

    Returns:
        The checkpoint, the trained model and the history.

    Raises:
        ConfigError: The image size or channels do not match the model, no training data,
            or training diverged (NaN or infinite loss or weights): nothing is written then.
    """
    cfg = config.resolved()
    assert cfg.model is not None and cfg.style is not None
    train = train.subset(train.labels >= 0)
    val = val.subset(val.labels >= 0)
    if len(train) == 0:
        raise ConfigError("training set is empty (no pair labelled normal or fault)")
    _, h, w, c = train.images.shape
    m = cfg.model
    if (h, w, c) != (m.input_size, m.input_size, m.in_channels):
        raise ConfigError(
            f"images are {h}x{w}x{c} but model {m.preset!r} expects "
            f"{m.input_size}x{m.input_size}x{m.in_channels}"
        )
    if m.metrics:
        for name, d in (("training", train), ("validation", val)):
            if d.metrics is None or d.metrics.shape[1] != len(m.metrics):
                raise ConfigError(
                    f"{name} data: model {m.preset!r} needs the metrics {m.metrics} next to "
                    "the images"
                )
    else:
        train.metrics = val.metrics = None
    if cfg.max_train is not None and len(train) > cfg.max_train:
        rng = np.random.default_rng(cfg.seed)
        train = train.subset(np.sort(rng.choice(len(train), cfg.max_train, replace=False)))

    rank, world = dist_rank_world()
    if rank != 0:
        out_dir = None  # rank 0 writes the checkpoint and the metrics, once
    where = f"{out_dir}: " if out_dir is not None else ""
    prev_threads = torch.get_num_threads()
    # the config's threads are per machine: processes on one machine share them
    torch.set_num_threads(max(1, cfg.threads // _local_world()) if world > 1 else cfg.threads)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    try:
        model = build_model(m)
        if train.metrics is not None:
            scaled = _with_hidden_odometry(train.metrics, model, cfg)
            model.set_metric_scaling(scaled.mean(axis=0), scaled.std(axis=0))
        if cfg.channels_last:
            model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        step_model: Any = model
        if world > 1:
            from torch.nn.parallel import DistributedDataParallel

            step_model = DistributedDataParallel(model)  # rank 0's initial weights
            # dropout: every rank its own masks (the same seed would repeat one mask per share)
            torch.manual_seed(cfg.seed + 7919 * rank)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = _make_schedule(opt, cfg, -(-len(train) // cfg.batch_size))
        log.info(
            "training %s (%d parameters) on %d images (%d fault), validating on %d",
            m.preset,
            count_parameters(model),
            len(train),
            int(train.labels.sum()),
            len(val),
        )
        history: list[dict[str, float]] = []
        best_key: tuple[float, float] | None = None
        best_state: dict[str, torch.Tensor] | None = None
        best_epoch, stale = 0, 0
        for epoch in range(1, cfg.epochs + 1):
            try:
                tl, ta, ips = _run_epoch(
                    step_model, train, cfg, opt, gen, f"epoch {epoch}/{cfg.epochs}", sched
                )
            except _DivergedError as exc:
                raise ConfigError(
                    f"{where}training diverged: the loss is {exc.loss} in epoch {epoch} "
                    f"(lr {cfg.lr:g}); no model was saved - lower lr"
                ) from None
            vl, va = tl, ta
            if len(val):
                if rank == 0:
                    vl, va, _ = _evaluate(model, val, cfg.channels_last)
                # one decision for every rank: rank 0's validation
                vl, va = _broadcast_floats([vl, va])
            history.append(
                {
                    "epoch": epoch,
                    "train_loss": tl,
                    "train_accuracy": ta,
                    "val_loss": vl,
                    "val_accuracy": va,
                    "images_per_s": ips,
                }
            )
            log.info(
                "epoch %d: train loss %.4f acc %.4f | val loss %.4f acc %.4f | %.0f img/s",
                epoch,
                tl,
                ta,
                vl,
                va,
                ips,
            )
            key = (va, -vl)
            if best_key is None or key > best_key:
                best_key, best_epoch, stale = key, epoch, 0
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            else:
                stale += 1
                if cfg.patience and stale >= cfg.patience:
                    log.info("early stop after epoch %d (best %d)", epoch, best_epoch)
                    break
        assert best_state is not None
        model.load_state_dict(best_state)
        model.eval()
        threshold = 0.5
        val_metrics: dict[str, float] = {}
        if len(val):
            acc_t = vl = va = 0.0
            if rank == 0:
                vl, va, vp = _evaluate(model, val, cfg.channels_last)
                threshold = metric_threshold(val.labels, vp, cfg.threshold_metric)
                acc_t = float(np.mean((vp >= threshold) == (val.labels == 1)))
            vl, va, threshold, acc_t = _broadcast_floats([vl, va, threshold, acc_t])
            val_metrics = {
                "val_loss": vl,
                "val_accuracy_at_0.5": va,
                "val_accuracy_at_threshold": acc_t,
            }
    finally:
        torch.set_num_threads(prev_threads)

    bad = _non_finite_weights(model)
    if bad:
        raise ConfigError(
            f"{where}training produced non-finite weights ({', '.join(bad[:3])}"
            f"{', ...' if len(bad) > 3 else ''}); no model was saved - lower lr"
        )
    if not 0.0 <= threshold <= 1.0:
        raise ConfigError(
            f"{where}the validation split gave the operating threshold {threshold}; "
            "no model was saved"
        )
    checkpoint = make_checkpoint(
        model,
        style=cfg.style,
        threshold=threshold,
        train_config=cfg.model_dump(mode="json"),
        label_thresholds=label_thresholds or {},
        matchers=matchers,
        odometry_noise=_odometry_noise_block(m),
        info={
            "best_epoch": best_epoch,
            "epochs_run": len(history),
            "n_train": len(train),
            "n_val": len(val),
            **({"processes": world} if world > 1 else {}),
            **val_metrics,
            **(data_info or {}),
        },
        history=history,
    )
    out_path = None
    if out_dir is not None:
        out_path = Path(out_dir)
        out_path.mkdir(parents=True, exist_ok=True)
        save_checkpoint(checkpoint, out_path / "model.pt")
        save_config(cfg, out_path)
        atomic_write_text(out_path / "history.json", json.dumps(history, indent=2))
        plot_history(
            history, out_path / "curves.png", title=f"{m.preset} (best epoch {best_epoch})"
        )
    return TrainResult(checkpoint=checkpoint, model=model, history=history, out_dir=out_path)


def make_checkpoint(
    model: FaultCNN,
    *,
    style: dict[str, Any],
    threshold: float,
    train_config: dict[str, Any] | None = None,
    label_thresholds: dict[str, Any] | None = None,
    info: dict[str, Any] | None = None,
    history: list[dict[str, float]] | None = None,
    matchers: Sequence[str] | None = None,
    odometry_noise: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The checkpoint dict: only plain types and tensors (loadable with ``weights_only``).

    ``matchers`` (the matchers whose matches the model was trained on) is stored as the
    ``matchers`` field when given; a checkpoint without it means ``icp-paper``.
    ``odometry_noise`` (the `scanguard.pairs.odometry.OdometryNoise` that scales the
    odometry disagreement) is stored for a model that reads it.
    """
    state = {
        k: v.detach().cpu().contiguous()
        for k, v in model.state_dict().items()  # contiguous: channels_last is not portable
    }
    extra: dict[str, Any] = {}
    if matchers is not None:
        extra["matchers"] = sorted({str(m) for m in matchers})
    if odometry_noise is not None:
        extra["odometry_noise"] = json.loads(json.dumps(odometry_noise))
    return {
        **extra,
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "model_config": model.config.model_dump(mode="json"),
        "style": dict(style),
        "threshold": float(threshold),
        "label_thresholds": json.loads(json.dumps(label_thresholds or {})),
        "train_config": json.loads(json.dumps(train_config or {})),
        "info": json.loads(json.dumps(info or {})),
        "history": json.loads(json.dumps(history or [])),
        "state_dict": state,
    }


def _odometry_noise_block(model: ModelConfig) -> dict[str, Any] | None:
    # the features were computed with the default noise model (`store_features`)
    if "has_odometry" not in model.metrics:
        return None
    from scanguard.pairs.odometry import OdometryNoise

    return OdometryNoise().model_dump(mode="json")


def save_checkpoint(checkpoint: dict[str, Any], path: str | Path) -> Path:
    """Write a checkpoint atomically (temp file, then rename)."""
    p = Path(path)
    with atomic_path(p) as tmp:
        torch.save(checkpoint, tmp)
    return p


def plot_history(history: list[dict[str, float]], path: str | Path, title: str = "") -> Path:
    """Loss and accuracy per epoch for train and validation (paper Figure 10) as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [h["epoch"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key in zip(axes, ["loss", "accuracy"], strict=True):
        ax.plot(ep, [h[f"train_{key}"] for h in history], "o-", label="train")
        ax.plot(ep, [h[f"val_{key}"] for h in history], "s-", label="validation")
        ax.set_xlabel("epoch")
        ax.set_ylabel(key)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    p = save_figure(fig, Path(path), dpi=100)
    return p


def load_store_images(
    store: str | Path | Any,
    style: dict[str, Any],
    *,
    splits: list[str] | None = None,
    environments: list[str] | None = None,
    exclude_environments: list[str] | None = None,
    include_ambiguous: bool = False,
    chunk: int = 512,
    metrics: list[str] | None = None,
) -> tuple[ImageSet, dict[str, Any]]:
    """Render the selected pairs of a `scanguard.dataset.PairStore` into memory.

    Args:
        store: A `PairStore` or anything `PairStore.open` accepts (build folder, ``.h5``).
        style: Render style fields.
        splits: Keep only these splits (``None``: all).
        environments: Keep only these environments (``None``: all).
        exclude_environments: Drop these environments.
        include_ambiguous: Keep pairs labelled -1.
        chunk: Pairs rendered per call (bounds the temporary memory).
        metrics: Also read these ICP metrics (`scanguard.detect.model.metric_inputs`) for a hybrid
            model.

    Returns:
        The images and the store's labelling rule (label thresholds of its first file).

    Raises:
        InputError: The store cannot be opened.
    """
    from scanguard.dataset import PairStore
    from scanguard.detect.images import render_all
    from scanguard.detect.render import RenderStyle

    if not isinstance(store, PairStore):
        p = Path(store)
        if not p.exists():
            raise InputError(p, "pair store not found")
        store = PairStore.open(p)
    idx = store.indices(splits, environment=environments, include_ambiguous=include_ambiguous)
    rec = store.records
    env = np.asarray(rec["environment"]).astype(str)
    if exclude_environments:
        idx = idx[~np.isin(env[idx], exclude_environments)]
    rs = RenderStyle(**style)
    images = render_all(store, idx, rs, batch_size=chunk, progress=len(idx) > 0)
    try:
        label_rule = store.label_config(0).model_dump(mode="json") if store.files else {}
    except Exception:  # a store without label metadata still trains; the rule is just unknown
        label_rule = {}
    metric_arr = None
    if metrics:
        from scanguard.detect.evaluate import store_features
        from scanguard.detect.model import metric_inputs
        from scanguard.pairs.profile import PROFILE_FEATURES

        profile = any(n in PROFILE_FEATURES for n in metrics)
        metric_arr = metric_inputs(store_features(store, idx, profile=profile), metrics)
    data = ImageSet(
        images,
        np.asarray(rec["label"], dtype=np.int64)[idx],
        env[idx],
        np.asarray(rec["sequence"]).astype(str)[idx],
        idx.astype(np.int64),
        metric_arr,
    )
    return data, label_rule


def train(config: TrainConfig, store: Any, out_dir: str | Path) -> TrainResult:
    """Train on a pair store: ``train_split`` for fitting, ``val_split`` for selection.

    Args:
        config: Training settings.
        store: A `scanguard.dataset.PairStore` or what `PairStore.open` accepts (build
            folder(s), ``.h5`` file(s)).
        out_dir: Output folder (created).

    Under ``torchrun`` (``WORLD_SIZE`` > 1) every process joins one process group
    (`init_distributed`) and trains with DistributedDataParallel: each global batch of
    ``batch_size`` images is split over the ranks, gradients are averaged, so the same
    config file gives the same training as one process. ``threads`` is shared by the
    processes of one machine. Only rank 0 writes ``out_dir``.

    Returns:
        The training result; the checkpoint is in ``out_dir/model.pt``.

    Raises:
        ConfigError: The store's build is unfinished (``complete: false``) and
            ``allow_incomplete`` is off, or training failed (see `train_images`).
    """
    cfg = config.resolved()
    assert cfg.style is not None
    from scanguard.dataset import PairStore

    init_distributed()  # under torchrun: one process group, rank 0 writes

    ps = store if isinstance(store, PairStore) else PairStore.open(store)
    if ps.incomplete and not cfg.allow_incomplete:
        path, why = ps.incomplete[0]
        raise ConfigError(
            f"{path}: incomplete dataset build ({why}); finish it by running the same "
            "`dataset build` command again, or set allow_incomplete: true to train anyway"
        )
    envs, excl = cfg.environments, cfg.exclude_environments
    assert cfg.model is not None
    names = list(cfg.model.metrics) or None
    tr, label_thresholds = load_store_images(
        ps,
        cfg.style,
        splits=cfg.train_split,
        environments=envs,
        exclude_environments=excl,
        metrics=names,
    )
    va, _ = load_store_images(
        ps,
        cfg.style,
        splits=cfg.val_split,
        environments=envs,
        exclude_environments=excl,
        metrics=names,
    )
    info = {
        "store": str(store) if isinstance(store, str | Path) else [str(f) for f in ps.files],
        "train_environments": sorted(set(tr.environment.tolist())),
    }
    return train_images(
        cfg,
        tr,
        va,
        out_dir,
        label_thresholds=label_thresholds,
        data_info=info,
        matchers=store_matchers(ps, tr.index) or None,
    )


def store_matchers(store: Any, index: ArrayLike) -> list[str]:
    """Names of the matchers (pair-file ``matcher`` attribute) of the pairs ``index`` of a store.

    Args:
        store: A `scanguard.dataset.PairStore`.
        index: Record indices of the pairs.

    Returns:
        The sorted distinct names; empty when no file records its matcher.
    """
    files = np.unique(np.asarray(store.records["file"])[np.asarray(index, dtype=np.int64)])
    names = {str(store.file_attrs[int(f)].get("matcher", "")) for f in files.tolist()}
    return sorted(n for n in names if n)
