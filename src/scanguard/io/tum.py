"""TUM trajectory files: ``stamp x y z qx qy qz qw`` per line (the evo / TUM RGB-D convention).

Only the planar part is kept on reading (x, y and the yaw of the quaternion); writing puts
``z = 0`` and a pure-yaw quaternion, so files open in evo and other TUM tools.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import FormatError, InputError
from scanguard.fsutil import atomic_write_text
from scanguard.geometry import quaternion_to_yaw, wrap_angle, yaw_to_quaternion

log = logging.getLogger(__name__)

__all__ = ["read_tum", "write_tum"]


def read_tum(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read a TUM trajectory file.

    Blank lines and lines starting with ``#`` are skipped. Commas are accepted as separators
    too (some tools write them).

    Args:
        path: The file.

    Returns:
        ``(stamps (N,), poses (N, 3))`` with poses ``(x, y, yaw)``, sorted by time.

    Raises:
        InputError: The file does not exist.
        FormatError: A line does not have 8 numbers, a quaternion is zero, or the file holds
            no poses; the message names the file and line number.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "TUM trajectory file not found")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(p, f"cannot read as text ({exc})") from None
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        tokens = s.replace(",", " ").split()
        if len(tokens) != 8:
            raise FormatError(
                p,
                f"expected 8 values (stamp x y z qx qy qz qw), found {len(tokens)}",
                location=f"line {lineno}",
            )
        rows.append(tokens)
        line_numbers.append(lineno)
    if not rows:
        raise FormatError(p, "no poses in TUM trajectory file")
    try:
        data = np.array(rows, dtype=np.float64)
    except ValueError:
        # Only on failure do we pay for finding the offending line.
        for tokens, lineno in zip(rows, line_numbers, strict=True):
            try:
                np.array(tokens, dtype=np.float64)
            except ValueError:
                raise FormatError(
                    p, f"not a number in {' '.join(tokens)!r}", location=f"line {lineno}"
                ) from None
        raise  # pragma: no cover - the loop above always finds the bad line
    bad = ~np.isfinite(data).all(axis=1)
    qnorm = np.linalg.norm(data[:, 4:8], axis=1)
    bad |= qnorm < 1e-9
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(
            p, "non-finite value or zero quaternion", location=f"line {line_numbers[i]}"
        )
    order = np.argsort(data[:, 0], kind="stable")
    if not np.all(order == np.arange(order.size)):
        log.warning("%s: poses are not in time order; sorted them", p)
        data = data[order]
    stamps = data[:, 0].copy()
    yaw = quaternion_to_yaw(data[:, 4:8] / qnorm[order, None])
    poses = np.stack([data[:, 1], data[:, 2], wrap_angle(yaw)], axis=1)
    return stamps, poses


def write_tum(path: str | Path, stamps: ArrayLike, poses: ArrayLike) -> Path:
    """Write planar poses as a TUM trajectory file (atomically).

    Args:
        path: Destination file.
        stamps: Times (s), shape ``(N,)``.
        poses: Poses ``(N, 3)`` as ``(x, y, yaw)``.

    Returns:
        The written path.

    Raises:
        InputError: Shapes do not match.
    """
    p = Path(path)
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    q = np.asarray(poses, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3 or q.shape[0] != t.size:
        raise InputError(
            p, f"need stamps (N,) and poses (N, 3) with the same N, got {t.shape} and {q.shape}"
        )
    quat = yaw_to_quaternion(q[:, 2])
    table = np.column_stack([t, q[:, 0], q[:, 1], np.zeros(t.size), quat])
    # Stamps keep nanoseconds; the other values use repr (the shortest text that reads back
    # to the same float), so a write/read round trip is exact up to the yaw/quaternion maths.
    lines = ["# timestamp x y z qx qy qz qw"]
    lines += [f"{row[0]:.9f} " + " ".join(repr(float(v)) for v in row[1:]) for row in table]
    atomic_write_text(p, "\n".join(lines) + "\n")
    return p
