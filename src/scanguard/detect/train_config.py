"""What a training run takes and gives: its settings, the rendered images and the result."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from scanguard.config import YamlModel
from scanguard.detect.model import FaultCNN, ModelConfig, get_preset
from scanguard.errors import ConfigError


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
