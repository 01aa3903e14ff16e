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
from scanguard.geometry import wrap_angle, yaw_to_quaternion
from scanguard.io.base import (
    MAX_COORDINATE,
    MAX_STAMP,
    QUATERNION_TOLERANCE,
    planar_yaw,
    printable,
    warn_once,
)
from scanguard.safeload import check_input_file

log = logging.getLogger(__name__)

__all__ = ["read_tum", "write_tum"]


def read_tum(
    path: str | Path, *, lenient: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read a TUM trajectory file.

    Blank lines and lines starting with ``#`` are skipped. Commas are accepted as separators
    too (some tools write them). Every other line must hold 8 numbers, all finite, with
    ``|x|, |y| <= 1e6`` m (`scanguard.io.base.MAX_COORDINATE`), ``|stamp| <= 1e12`` s
    (`scanguard.io.base.MAX_STAMP`) and a non-zero quaternion; a quaternion off unit norm
    is normalised with a warning. A UTF-8 byte-order mark and any line ending are accepted.

    Args:
        path: The file.
        lenient: Skip lines that break these rules (one warning gives their count) instead
            of refusing the file.

    Returns:
        ``(stamps (N,), poses (N, 3))`` with poses ``(x, y, yaw)``, sorted by time.

    Raises:
        InputError: The file does not exist.
        FormatError: A line does not have 8 numbers, a value is not finite or out of bounds,
            a quaternion is zero, the file is binary, or it holds no poses; the message names
            the file and line number.
    """
    p = Path(path)
    problems = _Problems(p, lenient)
    rows, line_numbers = _rows(_read_text(p), problems)
    data, ok = _table(rows, line_numbers, problems)
    _check_values(data, ok, line_numbers, problems)
    if problems.skipped:
        warn_once(
            log,
            p,
            f"lenient read: skipped {len(problems.skipped)} malformed line(s) "
            f"(first: {problems.skipped[0]})",
        )
    data = data[ok]
    if data.shape[0] == 0:
        raise FormatError(p, "no poses in TUM trajectory file")
    order = np.argsort(data[:, 0], kind="stable")
    if not np.all(order == np.arange(order.size)):
        warn_once(log, p, "poses are not in time order; sorted them")
        data = data[order]
    stamps = data[:, 0].copy()
    yaw, repaired, _ = planar_yaw(data[:, 4:8])  # zero quaternions were refused above
    if repaired.any():
        warn_once(
            log,
            p,
            f"{int(repaired.sum())} quaternion(s) off unit norm by more than "
            f"{QUATERNION_TOLERANCE}; normalised",
        )
    poses = np.stack([data[:, 1], data[:, 2], wrap_angle(yaw)], axis=1)
    return stamps, poses


class _Problems:
    """Malformed lines: raised at once (strict) or skipped and noted (lenient)."""

    def __init__(self, path: Path, lenient: bool) -> None:
        self.path = path
        self.lenient = lenient
        self.skipped: list[str] = []

    def __call__(self, lineno: int, what: str) -> None:
        if not self.lenient:
            raise FormatError(self.path, what, location=f"line {lineno}")
        self.skipped.append(f"line {lineno}: {what}")


def _read_text(p: Path) -> str:
    """The file's text; `InputError` if missing or unreadable, `FormatError` if binary."""
    check_input_file(p, what="TUM trajectory file")  # never open a FIFO or a device
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(p, f"cannot read ({exc.strerror or exc})") from None
    if b"\x00" in raw[:4096]:
        raise FormatError(p, "not a TUM trajectory file (binary data)")
    try:
        return raw.decode("utf-8-sig")  # a byte-order mark from a Windows editor is no value
    except UnicodeDecodeError as exc:
        raise FormatError(p, f"cannot read as text (byte {exc.start} is not UTF-8)") from None


def _rows(text: str, problem: _Problems) -> tuple[list[list[str]], list[int]]:
    """The tokens of every data line with 8 values, and their line numbers."""
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        tokens = s.replace(",", " ").split()
        if len(tokens) != 8:
            problem(lineno, f"expected 8 values (stamp x y z qx qy qz qw), found {len(tokens)}")
            continue
        rows.append(tokens)
        line_numbers.append(lineno)
    return rows, line_numbers


def _table(
    rows: list[list[str]], line_numbers: list[int], problem: _Problems
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The rows as numbers, and which of them parsed."""
    data = np.zeros((len(rows), 8))
    ok = np.ones(len(rows), dtype=bool)
    try:
        if rows:
            data = np.array(rows, dtype=np.float64)
    except ValueError:
        # Only on failure do we pay for finding the offending lines.
        for i, (tokens, lineno) in enumerate(zip(rows, line_numbers, strict=True)):
            for tok in tokens:
                try:
                    float(tok)
                except ValueError:
                    problem(lineno, f"not a number: {printable(tok)!r}")
                    ok[i] = False
                    break
            else:
                data[i] = np.array(tokens, dtype=np.float64)
    return data, ok


def _check_values(
    data: NDArray[np.float64], ok: NDArray[np.bool_], line_numbers: list[int], problem: _Problems
) -> None:
    """Clear ``ok`` where a value is not finite or out of bounds, or the quaternion is zero."""
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(data).all(axis=1)
        far = np.asarray((np.abs(data[:, 1:3]) > MAX_COORDINATE).any(axis=1), dtype=bool)
        late = np.asarray(np.abs(data[:, 0]) > MAX_STAMP, dtype=bool)
        qscale = np.abs(data[:, 4:8]).max(axis=1) if len(data) else np.zeros(0)
        zero_q = qscale < 1e-9
    for k in map(int, np.flatnonzero(ok & (~finite | far | late | zero_q))):
        names = ("stamp", "x", "y", "z", "qx", "qy", "qz", "qw")
        bad = [n for n, v in zip(names, data[k], strict=True) if not np.isfinite(v)]
        if bad:
            what = f"non-finite {', '.join(bad)}"
        elif far[k]:
            what = (
                f"coordinates ({data[k, 1]:.6g}, {data[k, 2]:.6g}) beyond +-{MAX_COORDINATE:.0e} m"
            )
        elif late[k]:
            what = f"stamp {data[k, 0]:.6g} s beyond +-{MAX_STAMP:.0e} s (nanoseconds?)"
        else:
            what = "zero quaternion"
        problem(line_numbers[k], what)
        ok[k] = False


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
