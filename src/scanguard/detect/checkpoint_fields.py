"""Fields of a detector checkpoint that are read without PyTorch.

The matchers a model was trained on and its operating threshold: `scanguard.detect.detector`
reads them from a checkpoint's metadata, which it can have from the cache without loading the
weights (`scanguard.detect.checkpoint` re-exports them).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from scanguard.errors import ModelError

#: Matcher of the data a checkpoint without a ``matchers`` field was trained on (the shipped
#: model and every checkpoint written before the field existed: the paper's ICP).
LEGACY_MATCHER = "icp-paper"


def checkpoint_matchers(ckpt: Mapping[str, Any], source: str | Path) -> tuple[str, ...]:
    """The matchers a checkpoint's model was trained on (``matchers`` field).

    A checkpoint without the field was trained on `LEGACY_MATCHER` matches.

    Raises:
        ModelError: The field is not a non-empty list of names; the message names ``source``.
    """
    value = ckpt.get("matchers")
    if value is None:
        return (LEGACY_MATCHER,)
    if (
        isinstance(value, str)
        or not isinstance(value, Sequence)
        or not value
        or not all(isinstance(v, str) and v for v in value)
    ):
        raise ModelError(f"{source}: checkpoint 'matchers' {value!r} is not a list of names")
    return tuple(value)


def check_threshold(value: Any, source: str | Path) -> float:
    """The operating threshold as a float, checked to be a probability in ``[0, 1]``.

    Raises:
        ModelError: Not a number, NaN, or outside ``[0, 1]``; the message names ``source``.
    """
    try:
        t = float(value)
    except (TypeError, ValueError):
        raise ModelError(f"{source}: operating threshold {value!r} is not a number") from None
    if not 0.0 <= t <= 1.0:
        raise ModelError(f"{source}: operating threshold {t} is not a probability in [0, 1]")
    return t


__all__ = ["LEGACY_MATCHER", "check_threshold", "checkpoint_matchers"]
