"""The detector checkpoint: its contract, writing, reading and validation.

`scanguard.detect.train` writes checkpoints (`make_checkpoint`, `save_checkpoint`) and
`scanguard.detect.detector` reads them (`load_checkpoint`, `model_from_checkpoint`); both
import this module, which imports neither.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from pydantic import ValidationError

from scanguard.detect.calibrate import Calibration
from scanguard.detect.checkpoint_fields import LEGACY_MATCHER, check_threshold, checkpoint_matchers
from scanguard.detect.model import FaultCNN, ModelConfig, build_model
from scanguard.detect.render import RenderStyle
from scanguard.errors import ConfigError, ModelError
from scanguard.fsutil import atomic_path
from scanguard.pairs.labels import LabelConfig
from scanguard.safeload import check_input_file

#: The ``format`` field of a checkpoint written by `save_checkpoint`.
CHECKPOINT_FORMAT = "scanguard-fault-cnn"
#: The newest checkpoint layout this version reads and writes (2: adds the optional
#: ``calibration`` block of `scanguard.detect.calibrate`).
CHECKPOINT_VERSION = 2
#: The version a checkpoint with a ``calibration`` block is written with, so that an older
#: scanguard, which would silently ignore the block, refuses it instead.
CALIBRATED_VERSION = 2


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read and validate a checkpoint written by `scanguard.detect.checkpoint.save_checkpoint`.

    Raises:
        ModelError: The file is missing, not a checkpoint, corrupt, its weights do not fit
            the architecture it declares, or its ``calibration`` block is malformed; the
            message names the file.
    """
    p = Path(path)
    check_input_file(p, what="model file", error=ModelError)  # never open a FIFO or device
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        # any file can be given here (a YAML config, a picture): torch's unpickler fails on
        # foreign bytes with whatever it meets first (IndexError, UnicodeDecodeError, ...)
        raise ModelError(f"{p}: not a readable model checkpoint ({type(exc).__name__})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ModelError(f"{p}: not a scanguard fault-detector checkpoint")
    _check_fields(ckpt, p)
    if ckpt.get("calibration") is not None:
        Calibration.from_dict(ckpt["calibration"], p)
    state = ckpt["state_dict"]
    if isinstance(state, Mapping):
        bad = [
            str(name)
            for name, t in state.items()
            if isinstance(t, torch.Tensor)
            and t.is_floating_point()
            and not bool(torch.isfinite(t).all())
        ]
        if bad:
            shown = ", ".join(bad[:3]) + (", ..." if len(bad) > 3 else "")
            raise ModelError(f"{p}: checkpoint has non-finite weights ({shown})")
    return dict(ckpt)


def _check_fields(ckpt: Mapping[str, Any], p: Path) -> None:
    """The checkpoint's version, style, threshold and labelling rule have their types.

    A hand-edited or foreign file must fail here, in one line, not later with a traceback
    deep in the detector or the run.

    Raises:
        ModelError: A field is missing or of the wrong type or value; names the file.
    """
    version = ckpt.get("version", 0)
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise ModelError(f"{p}: checkpoint version {_short(version)} is not a whole number")
    if version > CHECKPOINT_VERSION:
        raise ModelError(
            f"{p}: checkpoint version {version} is newer than supported ({CHECKPOINT_VERSION})"
        )
    for key in ("model_config", "style", "threshold", "state_dict"):
        if key not in ckpt:
            raise ModelError(f"{p}: checkpoint lacks {key!r}")
    for key in ("model_config", "style", "state_dict"):
        if not isinstance(ckpt[key], Mapping):
            raise ModelError(f"{p}: checkpoint {key!r} {_short(ckpt[key])} is not a mapping")
    try:
        RenderStyle.model_validate(dict(ckpt["style"]))
    except ValidationError as exc:
        raise ModelError(f"{p}: invalid render style in checkpoint ({_first(exc)})") from None
    check_threshold(ckpt["threshold"], p)
    rule = ckpt.get("label_thresholds")
    if rule is not None:
        if not isinstance(rule, Mapping):
            raise ModelError(f"{p}: checkpoint 'label_thresholds' {_short(rule)} is not a mapping")
        try:
            LabelConfig.from_dict(dict(rule), source=f"{p}: checkpoint 'label_thresholds'")
        except ConfigError as exc:
            raise ModelError(str(exc)) from None


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:37]}..."


def _first(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err["loc"]) or "<root>"
    return f"{loc}: {err['msg']}"


def model_from_checkpoint(ckpt: dict[str, Any], source: str | Path = "<checkpoint>") -> FaultCNN:
    """Rebuild the network of a checkpoint and load its weights.

    Raises:
        ModelError: Invalid architecture, or weights that do not match it.
    """
    try:
        cfg = ModelConfig.model_validate(ckpt["model_config"])
        model = build_model(cfg)
    except (ValidationError, ValueError) as exc:
        raise ModelError(f"{source}: invalid model config in checkpoint ({exc})") from None
    except Exception as exc:  # ConfigError from check()
        raise ModelError(f"{source}: invalid model config in checkpoint ({exc})") from None
    try:
        model.load_state_dict(ckpt["state_dict"], strict=True)
    except (RuntimeError, KeyError, TypeError) as exc:
        first = str(exc).strip().splitlines()
        detail = " ".join(line.strip() for line in first[:3])
        raise ModelError(
            f"{source}: weights do not match the {cfg.preset!r} architecture ({detail})"
        ) from None
    model.eval()
    return model


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


def save_checkpoint(checkpoint: dict[str, Any], path: str | Path) -> Path:
    """Write a checkpoint atomically (temp file, then rename)."""
    p = Path(path)
    with atomic_path(p) as tmp:
        torch.save(checkpoint, tmp)
    return p


def with_calibration(checkpoint: Mapping[str, Any], calibration: Calibration) -> dict[str, Any]:
    """The checkpoint plus the ``calibration`` block (weights and everything else unchanged).

    The top-level ``threshold`` stays the training one; a detector uses the block's.
    """
    out = dict(checkpoint)
    out["calibration"] = calibration.to_dict()
    out["version"] = max(int(out.get("version", 1)), CALIBRATED_VERSION)
    return out


__all__ = [
    "CALIBRATED_VERSION",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "LEGACY_MATCHER",
    "check_threshold",
    "checkpoint_matchers",
    "load_checkpoint",
    "make_checkpoint",
    "model_from_checkpoint",
    "save_checkpoint",
    "with_calibration",
]
