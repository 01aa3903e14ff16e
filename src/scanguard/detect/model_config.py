"""What a fault-detection CNN reads and how it is built, without PyTorch.

The architecture (`ModelConfig`) and the metric inputs of a hybrid model (`metric_inputs`):
everything a detector needs to run an exported network with onnxruntime, so that loading the
shipped model for a run does not import PyTorch (~1.4 s) when its ONNX export is cached
(`scanguard.detect.detector`). `scanguard.detect.model` builds the PyTorch network from
these and re-exports them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, field_validator

from scanguard.config import YamlModel
from scanguard.detect.features import with_derived_features
from scanguard.errors import ConfigError
from scanguard.pairs.odometry import ODOMETRY_FEATURES
from scanguard.pairs.profile import PROFILE_FEATURES

#: Class index of each label (fault is the positive class).
CLASS_NAMES: tuple[str, str] = ("normal", "fault")

#: Scale-free ICP quality metrics the hybrid (``cnn+metrics``) preset reads next to the image.
#: Motion size (translation / rotation) and raw point counts are deliberately absent: they
#: depend on the robot speed and the sensor and did not transfer to held-out data.
METRIC_FEATURES: tuple[str, ...] = (
    "mean_residual",
    "median_residual",
    "inlier_ratio",
    "eig_min_per_inlier",
    "gmapping_score_norm",
    "iterations",
    "converged",
)

#: The hybrid model that also reads the odometry disagreement (`scanguard.pairs.odometry`):
#: the ICP metrics plus ``odom_trans_z``, ``odom_rot_z`` and the ``has_odometry`` mask.
ODOMETRY_METRIC_FEATURES: tuple[str, ...] = (*METRIC_FEATURES, *ODOMETRY_FEATURES)

#: The odometry hybrid plus the per-beam residual profile (`scanguard.pairs.profile`).
PROFILE_METRIC_FEATURES: tuple[str, ...] = (*ODOMETRY_METRIC_FEATURES, *PROFILE_FEATURES)

# Heavy-tailed metrics enter as log10 of the value clipped to this floor.
_LOG_FLOOR = {"mean_residual": 1e-4, "median_residual": 1e-4, "eig_min_per_inlier": 1e-6}
# Disagreements in standard deviations enter as log1p: 0 (no odometry, or perfect agreement)
# stays 0, so the mask's own weight carries "no information".
_LOG1P = frozenset({"odom_trans_z", "odom_rot_z"})
# Value of a NaN metric (no match possible): a large residual, nothing else. An infinite
# disagreement (the match failed while odometry exists) is a very large one.
_NAN_FILL = {"mean_residual": 10.0, "median_residual": 10.0, "odom_trans_z": 1e6, "odom_rot_z": 1e6}


def metric_inputs(
    features: Mapping[str, ArrayLike] | NDArray[np.floating[Any]], names: Sequence[str]
) -> NDArray[np.float32]:
    """The metric vector ``(N, K)`` a hybrid model reads (before its own standardisation).

    Args:
        features: Metric columns by name (a pair store's records or ``MatchResult.metrics()``
            values; ``gmapping_score_norm`` and ``eig_min_per_inlier`` may be derived, see
            `scanguard.detect.features.with_derived_features`), or an already transformed
            ``(N, K)`` array, returned as float32.
        names: Metric names in model order (`ModelConfig.metrics`).

    Returns:
        float32 ``(N, K)``: log10 of residuals and eigenvalue, the others as they are; NaN
        replaced (residuals by a large value, others by 0).

    Raises:
        ConfigError: A metric is missing.
    """
    if not isinstance(features, Mapping):
        arr = np.asarray(features, dtype=np.float32)
        if arr.ndim != 2 or arr.shape[1] != len(names):
            raise ConfigError(f"metric inputs: expected (N, {len(names)}) array, got {arr.shape}")
        return arr
    cols = with_derived_features(features)
    missing = [n for n in names if n not in cols]
    if missing:
        raise ConfigError(f"metric inputs: missing metric(s) {missing}; have {sorted(cols)}")
    out = []
    for n in names:
        v = np.asarray(cols[n], dtype=np.float64).reshape(-1)
        v = np.where(np.isfinite(v), v, _NAN_FILL.get(n, 0.0))
        if n in _LOG_FLOOR:
            v = np.log10(np.maximum(v, _LOG_FLOOR[n]))
        elif n in _LOG1P:
            v = np.log1p(np.maximum(v, 0.0))
        out.append(v)
    return np.stack(out, axis=1).astype(np.float32) if out else np.zeros((0, 0), np.float32)


class ModelConfig(YamlModel):
    """Architecture of a fault-detection CNN.

    Attributes:
        preset: Name of the preset this config came from (informational).
        in_channels: Image channels (3 for the paper's RGB images, 2 for occupancy, 2 per view
            for multiscale).
        input_size: Square input side in pixels; must be divisible by ``2 ** len(widths)``.
        widths: Output channels of the five conv blocks.
        dense: Hidden fully connected layer sizes (before the 2-unit output layer).
        kernel_size: Conv kernel size (odd; "same" padding).
        conv_dropout: Dropout after every max-pool (paper: 0.25).
        dense_dropout: Dropout before the output layer.
        metrics: ICP quality metrics (`METRIC_FEATURES` names) read next to the image by a
            hybrid model; empty for the image-only CNN.
        metric_hidden: Width of the hidden layer the standardised metrics pass through before
            they join the flattened image features; 0 = late fusion: a linear term of the
            standardised metrics is added to the image logits (a logistic regression on the
            metrics trained jointly with the CNN, which extrapolates to unseen sensors more
            predictably than a hidden layer).
    """

    preset: str = "custom"
    in_channels: int = Field(default=3, ge=1, le=16)
    input_size: int = Field(default=256, ge=8)
    widths: list[int] = Field(default_factory=lambda: [32, 64, 128, 128, 256], min_length=1)
    dense: list[int] = Field(default_factory=lambda: [256])
    kernel_size: int = Field(default=3, ge=1)
    conv_dropout: float = Field(default=0.25, ge=0.0, lt=1.0)
    dense_dropout: float = Field(default=0.5, ge=0.0, lt=1.0)
    metrics: list[str] = Field(default_factory=list)
    metric_hidden: int = Field(default=16, ge=0)

    @field_validator("kernel_size")
    @classmethod
    def _odd_kernel(cls, v: int) -> int:
        if v % 2 != 1:
            raise ValueError(f"kernel_size must be odd, got {v}")
        return v

    @property
    def feature_size(self) -> int:
        """Spatial side of the last feature map."""
        return self.input_size // (2 ** len(self.widths))

    def check(self) -> None:
        """Raise `ConfigError` if the input size does not survive the pooling stack."""
        if self.input_size % (2 ** len(self.widths)) != 0:
            raise ConfigError(
                f"model config: input_size {self.input_size} is not divisible by "
                f"2**{len(self.widths)} (one 2x2 max-pool per conv block)"
            )


__all__ = [
    "CLASS_NAMES",
    "METRIC_FEATURES",
    "ODOMETRY_METRIC_FEATURES",
    "PROFILE_METRIC_FEATURES",
    "ModelConfig",
    "metric_inputs",
]
