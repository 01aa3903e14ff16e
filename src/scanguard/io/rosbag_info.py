"""Checks of what a bag says about itself: our writer's info JSON and ``/tf_static``.

Both come from the file, so both are hostile input: the info message may hold any JSON (a
list, ``null``, a string where an object belongs, arrays nested 100k deep), a static transform
any number (1e300, NaN, a zero or scaled quaternion). Each is checked here against the
domain the reader relies on, so a bad value is a `FormatError` naming the bag and the topic,
never a traceback or a silently wrong laser offset.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError
from scanguard.io.base import (
    LENIENT_HINT,
    MAX_COORDINATE,
    QUATERNION_TOLERANCE,
    planar_yaw,
    printable,
    warn_once,
)

log = logging.getLogger(__name__)

__all__ = ["INFO_TOPIC", "TF_STATIC", "check_info", "laser_offset_of", "parse_info"]

INFO_TOPIC = "/scanguard/info"
TF_STATIC = "/tf_static"
MAX_INFO_BYTES = 16 * 2**20
"""Largest info message read (our writer's are a few KB)."""

# key -> the JSON types it may hold (None always allowed: "not recorded")
_INFO_KEYS: dict[str, tuple[type, ...]] = {
    "name": (str,),
    "sensor": (dict,),
    "metadata": (dict,),
    "laser_offset": (list,),
    "reference_kind": (str,),
    "scan_topic": (str,),
    "odom_topic": (str,),
    "reference_topic": (str,),
}
_JSON_TYPE: dict[type, str] = {str: "a string", dict: "an object", list: "a list"}


def parse_info(path: Path, text: str) -> dict[str, Any]:
    """The info message's JSON, checked (see `check_info`); `FormatError` if it is not."""
    if len(text) > MAX_INFO_BYTES:
        raise FormatError(
            path, f"info message of {len(text)} bytes is too large", location=f"topic {INFO_TOPIC}"
        )
    try:
        value = json.loads(text)
    except RecursionError:
        raise FormatError(
            path, "info message nested too deeply", location=f"topic {INFO_TOPIC}"
        ) from None
    except ValueError as exc:  # JSONDecodeError, or a number too long to convert
        raise FormatError(
            path,
            f"info message is not JSON ({printable(str(exc), 80)})",
            location=f"topic {INFO_TOPIC}",
        ) from None
    return check_info(path, value)


def check_info(path: Path, value: Any) -> dict[str, Any]:
    """Check the decoded info JSON: an object whose known keys hold the expected types.

    Args:
        path: The bag (for messages).
        value: The decoded JSON.

    Returns:
        ``value`` (an object; unknown keys are kept, they are never read).

    Raises:
        FormatError: It is not an object, a known key holds the wrong type, the sensor's rate
            is not a positive number, or the laser offset is not 3 finite numbers within
            `MAX_COORDINATE`.
    """

    def bad(what: str) -> FormatError:
        return FormatError(path, f"info message: {what}", location=f"topic {INFO_TOPIC}")

    if not isinstance(value, dict):
        raise bad(f"expected a JSON object, found {type(value).__name__}")
    for key, types in _INFO_KEYS.items():
        v = value.get(key)
        if v is not None and not isinstance(v, types):
            raise bad(f"{key!r} must be {_JSON_TYPE[types[0]]}, found {type(v).__name__}")
    sensor = value.get("sensor") or {}
    rate = sensor.get("rate_hz")
    if rate is not None and not (_is_number(rate) and math.isfinite(rate) and rate > 0):
        raise bad(f"sensor rate_hz must be a positive number, found {printable(repr(rate))}")
    if sensor.get("name") is not None and not isinstance(sensor["name"], str):
        raise bad("sensor name must be a string")
    offset = value.get("laser_offset")
    if offset is not None:
        if len(offset) != 3 or not all(_is_number(v) and math.isfinite(v) for v in offset):
            raise bad(f"laser_offset must be 3 finite numbers, found {printable(repr(offset))}")
        if max(abs(offset[0]), abs(offset[1])) > MAX_COORDINATE:
            raise bad(f"laser_offset {printable(repr(offset))} beyond +-{MAX_COORDINATE:.0e} m")
    return value


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def laser_offset_of(
    path: Path, info: dict[str, Any], statics: list[Any], frame_id: str, lenient: bool
) -> NDArray[np.float64]:
    """The laser offset: our writer's, else the static transform to the scan frame, else 0.

    A transform whose translation is not finite or beyond `MAX_COORDINATE`, or whose rotation
    is zero or not finite, is a `FormatError` (lenient: ignored with a warning); a rotation
    whose norm is off by more than `QUATERNION_TOLERANCE` is normalised with a warning.
    """
    if info.get("laser_offset") is not None:
        return np.asarray(info["laser_offset"], dtype=np.float64)
    norm = frame_id.strip().lstrip("/")
    for tf in statics:
        if not frame_id or tf.child_frame_id.strip().lstrip("/") != norm:
            continue
        tr, q = tf.transform.translation, tf.transform.rotation
        yaw, repaired, unusable = planar_yaw(np.array([q.x, q.y, q.z, q.w]))
        xy = np.array([tr.x, tr.y], dtype=np.float64)
        problem = None
        if not np.isfinite(xy).all() or np.abs(xy).max() > MAX_COORDINATE:
            problem = (
                f"translation ({tr.x:.6g}, {tr.y:.6g}) is not finite or beyond "
                f"+-{MAX_COORDINATE:.0e} m"
            )
        elif unusable[0]:
            problem = "rotation is a zero or non-finite quaternion"
        if problem is not None:
            what = f"transform to {printable(frame_id)}: {problem}"
            if not lenient:
                raise FormatError(path, what + LENIENT_HINT, location=f"topic {TF_STATIC}")
            warn_once(log, path, f"topic {TF_STATIC}: ignored {what}")
            continue
        if repaired[0]:
            norm_q = math.sqrt(q.x**2 + q.y**2 + q.z**2 + q.w**2)
            warn_once(
                log,
                path,
                f"topic {TF_STATIC}: rotation of the transform to {printable(frame_id)} has "
                f"norm {norm_q:.6g} (tolerance {QUATERNION_TOLERANCE}); normalised",
            )
        return np.array([xy[0], xy[1], float(yaw[0])])
    return np.zeros(3)
