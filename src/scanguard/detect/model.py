"""The fault-detection CNN (paper Section 3.3, Figure 9) and its compact variant.

The paper describes the network only in words (its Figure 9 is not legible in our copy):
a 256x256x3 input in ``[0, 1]``; five ``Conv2d + ReLU`` blocks, each followed by 2x2
max-pooling and dropout 0.25; flatten; fully connected layers; softmax over
``{normal, fault}``; binary cross-entropy; Adam; 17 epochs; batch 32.

The widths we chose for the ``paper`` preset (3x3 kernels, "same" padding):

========  ======================  ==============
block     conv channels           output (HxW)
========  ======================  ==============
1         3 -> 32                 128 x 128
2         32 -> 64                64 x 64
3         64 -> 128               32 x 32
4         128 -> 128              16 x 16
5         128 -> 256              8 x 8
dense     16384 -> 256 -> 2       (ReLU, dropout 0.5 before the output layer)
========  ======================  ==============

The ``compact`` preset (the shipped default) keeps the block structure but halves every width,
reads a smaller 2-channel (previous / current occupancy) 64x64 image and uses lighter dropout
(none after the conv blocks, 0.25 before the output): with the paper's dropout the small network
underfit (train accuracy ~83%), and the lighter setting scored higher on validation, test and
the held-out office (docs/model_card.md); see `PRESETS`.

The ``multiscale`` preset is the compact network on 6-channel 64x64 images (render style
``multiscale``: the auto-fitted occupancy view plus metric crops at 0.05 and 0.2 m/px). The
``cnn+metrics`` preset (hybrid) also reads seven scale-free ICP quality metrics
(`METRIC_FEATURES`, transformed by `metric_inputs` and standardised inside the network);
with ``metric_hidden = 0`` they enter as a linear term added to the image logits (late
fusion), otherwise through a small hidden layer concatenated to the flattened image features.

The network outputs two logits; the probability of a fault is ``softmax(logits)[:, 1]``.
Keras' ``binary_crossentropy`` on a 2-unit softmax with one-hot targets equals the 2-class
cross-entropy (both units carry the same per-sample term), so training uses
`torch.nn.functional.cross_entropy`.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import nn

from scanguard.detect.model_config import (
    CLASS_NAMES,
    METRIC_FEATURES,
    ODOMETRY_METRIC_FEATURES,
    PROFILE_METRIC_FEATURES,
    ModelConfig,
    metric_inputs,
)
from scanguard.errors import ConfigError

log = logging.getLogger(__name__)

PresetName = Literal[
    "paper",
    "compact",
    "multiscale",
    "cnn+metrics",
    "cnn+metrics+odometry",
    "cnn+metrics+odometry+profile",
    "compact128",
    "tiny",
]


#: Named architectures. ``paper`` is the paper's network; ``cnn+metrics`` is the shipped
#: default (half widths, 6-channel 64x64 multiscale input, ICP metrics fused into the output);
#: ``multiscale`` is its image-only twin; ``compact`` (2-channel 64x64) the previous default,
#: ``compact128`` the same at 128x128; ``tiny`` is for tests only.
def _half(preset: str, in_channels: int, **extra: Any) -> ModelConfig:
    # the paper's block layout at half width on 64x64 inputs, with dropout only in the
    # dense layers: what the compact, multiscale and shipped hybrid presets share
    return ModelConfig(
        preset=preset,
        in_channels=in_channels,
        input_size=64,
        widths=[16, 32, 64, 64, 128],
        dense=[128],
        conv_dropout=0.0,
        dense_dropout=0.25,
        **extra,
    )


PRESETS: dict[str, ModelConfig] = {
    "paper": ModelConfig(
        preset="paper", in_channels=3, input_size=256, widths=[32, 64, 128, 128, 256], dense=[256]
    ),
    "compact": _half("compact", 2),
    "multiscale": _half("multiscale", 6),
    "cnn+metrics": _half("cnn+metrics", 6, metrics=list(METRIC_FEATURES), metric_hidden=0),
    "cnn+metrics+odometry": _half(
        "cnn+metrics+odometry", 6, metrics=list(ODOMETRY_METRIC_FEATURES), metric_hidden=0
    ),
    "cnn+metrics+odometry+profile": _half(
        "cnn+metrics+odometry+profile", 6, metrics=list(PROFILE_METRIC_FEATURES), metric_hidden=0
    ),
    "compact128": ModelConfig(
        preset="compact128",
        in_channels=2,
        input_size=128,
        widths=[16, 32, 64, 64, 128],
        dense=[128],
    ),
    "tiny": ModelConfig(
        preset="tiny", in_channels=2, input_size=32, widths=[8, 8, 16, 16, 16], dense=[16]
    ),
}


def get_preset(name: str) -> ModelConfig:
    """A copy of the preset ``name``.

    Raises:
        ConfigError: Unknown preset name.
    """
    if name not in PRESETS:
        raise ConfigError(f"unknown model preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name].model_copy(deep=True)


class FaultCNN(nn.Module):
    """Conv blocks (conv, ReLU, 2x2 max-pool, dropout) then dense layers to two logits."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        config.check()
        self.config = config
        blocks: list[nn.Module] = []
        c_in = config.in_channels
        pad = config.kernel_size // 2
        for w in config.widths:
            blocks += [
                nn.Conv2d(c_in, w, config.kernel_size, padding=pad),
                nn.ReLU(inplace=True),
                nn.MaxPool2d(2),
                nn.Dropout(config.conv_dropout),
            ]
            c_in = w
        self.features = nn.Sequential(*blocks)
        head: list[nn.Module] = [nn.Flatten()]
        n_in = c_in * config.feature_size**2
        k = len(config.metrics)
        self.metric_net: nn.Module | None = None
        self.metric_mean: torch.Tensor
        self.metric_std: torch.Tensor
        if k:
            # standardisation of the metric inputs, fitted on the training data
            self.register_buffer("metric_mean", torch.zeros(k))
            self.register_buffer("metric_std", torch.ones(k))
            if config.metric_hidden:
                self.metric_net = nn.Sequential(nn.Linear(k, config.metric_hidden), nn.ReLU())
                n_in += config.metric_hidden
            else:
                self.metric_net = nn.Linear(k, len(CLASS_NAMES))
        for d in config.dense:
            head += [nn.Linear(n_in, d), nn.ReLU(inplace=True)]
            n_in = d
        head += [nn.Dropout(config.dense_dropout), nn.Linear(n_in, len(CLASS_NAMES))]
        self.classifier = nn.Sequential(*head)

    @property
    def uses_metrics(self) -> bool:
        """Whether `forward` needs the ICP metric vector next to the image."""
        return self.metric_net is not None

    def set_metric_scaling(self, mean: ArrayLike, std: ArrayLike) -> None:
        """Store the standardisation of the metric inputs (per-feature mean and std)."""
        m = torch.as_tensor(np.asarray(mean, dtype=np.float32))
        sd_in = np.asarray(std, dtype=np.float32)
        # a column constant in the training data is left unscaled: dividing by a tiny std
        # would turn any other value it takes later into an enormous input
        sd = torch.as_tensor(np.where(sd_in > 1e-6, sd_in, np.float32(1.0)))
        self.metric_mean.copy_(m)
        self.metric_std.copy_(sd)

    def forward(self, x: torch.Tensor, metrics: torch.Tensor | None = None) -> torch.Tensor:
        """Logits ``(B, 2)`` for images ``(B, C, H, W)`` in ``[0, 1]``.

        A hybrid model also needs ``metrics`` ``(B, K)`` from `metric_inputs`.
        """
        f = self.features(x)
        if self.metric_net is None:
            return self.classifier(f)
        if metrics is None:
            raise ConfigError(f"model {self.config.preset!r} needs the ICP metrics input")
        z = self.metric_net((metrics - self.metric_mean) / self.metric_std)
        if not self.config.metric_hidden:
            return self.classifier(f) + z
        return self.classifier(torch.cat([torch.flatten(f, 1), z], dim=1))

    @torch.no_grad()
    def fault_probability(
        self, x: torch.Tensor, metrics: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Softmax probability of the fault class, ``(B,)``."""
        return torch.softmax(self.forward(x, metrics), dim=1)[:, 1]


def build_model(preset: str | ModelConfig = "compact") -> FaultCNN:
    """Build an (untrained) fault-detection CNN.

    Args:
        preset: A preset name from `PRESETS` or a full `ModelConfig`.

    Returns:
        The network in eval mode on the CPU.

    Raises:
        ConfigError: Unknown preset, or an input size the pooling stack cannot handle.
    """
    cfg = get_preset(preset) if isinstance(preset, str) else preset
    model = FaultCNN(cfg)
    model.eval()
    return model


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return int(sum(p.numel() for p in model.parameters() if p.requires_grad))


def images_to_tensor(images: NDArray[np.uint8], channels_last: bool = True) -> torch.Tensor:
    """uint8 ``(B, H, W, C)`` -> float32 ``(B, C, H, W)`` in ``[0, 1]``."""
    t = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)
    if channels_last:
        return t.contiguous(memory_format=torch.channels_last)
    return t.contiguous()


def forward_numpy(
    model: FaultCNN, chunk: NDArray[np.uint8], metrics: NDArray[np.float32] | None, raw: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The detector's PyTorch back end: logits of uint8 images ``(B, H, W, C)`` as float64.

    With ``raw`` also the fault probabilities (softmax in float64), else None.
    """
    with torch.inference_mode():
        mt = None if metrics is None else torch.from_numpy(metrics)
        logits = model(images_to_tensor(chunk, channels_last=True), mt)
        proba = torch.softmax(logits.double(), dim=1)[:, 1].numpy() if raw else None
        return logits.double().numpy(), proba


def inference_ready(model: FaultCNN) -> FaultCNN:
    """``model`` in eval mode and channels-last (the layout `forward_numpy` feeds)."""
    return model.eval().to(memory_format=torch.channels_last)  # type: ignore[call-overload]


__all__ = [
    "CLASS_NAMES",
    "METRIC_FEATURES",
    "ODOMETRY_METRIC_FEATURES",
    "PRESETS",
    "PROFILE_METRIC_FEATURES",
    "FaultCNN",
    "ModelConfig",
    "PresetName",
    "build_model",
    "count_parameters",
    "forward_numpy",
    "get_preset",
    "images_to_tensor",
    "inference_ready",
    "metric_inputs",
]
