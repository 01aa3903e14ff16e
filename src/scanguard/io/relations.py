"""Reference relations of the Freiburg SLAM benchmark (Kümmerle et al. 2009).

A ``*.relations`` file holds one relation per line: ``t1 t2 x y z roll pitch yaw``, the
relative pose of the robot from time ``t1`` to time ``t2`` (m, rad). ``t1`` and ``t2`` equal
the ``ipc_timestamp`` of FLASER lines of the matching CARMEN log. Only the planar part
``(x, y, yaw)`` is kept; ``z``, ``roll`` and ``pitch`` are read (and must be numbers) but
dropped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError
from scanguard.io.base import MAX_COORDINATE, MAX_STAMP, printable, read_file_bytes, warn_once

log = logging.getLogger(__name__)

__all__ = ["RELATION_COLUMNS", "Relations", "read_relations"]

SAME_TIME_MOTION = 1e-6
"""Largest motion (m, rad) of a relation from a time to the same time; more is refused."""

RELATION_COLUMNS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")
#: Largest ``|roll|``, ``|pitch|``, ``|yaw|`` (rad) of a relation: a few turns, unwrapped.
MAX_RELATION_ANGLE = 100.0
"""The values of one line of a relations file, in order."""


@dataclass(frozen=True)
class Relations:
    """Reference relations read from one file.

    Attributes:
        t1: Start stamps (s), shape ``(M,)``.
        t2: End stamps (s), shape ``(M,)``.
        delta: Relative poses ``(x, y, yaw)`` of the robot at ``t2`` in its frame at ``t1``,
            shape ``(M, 3)`` (m, m, rad).
        path: The file they were read from.
    """

    t1: NDArray[np.float64]
    t2: NDArray[np.float64]
    delta: NDArray[np.float64]
    path: str

    def __len__(self) -> int:
        """Number of relations."""
        return int(self.t1.shape[0])


def _read_text(path: Path) -> str:
    """The file's text, gunzipped when it starts with the gzip magic."""
    data = read_file_bytes(path, log, missing="relations file not found")
    data = data.removeprefix(b"\xef\xbb\xbf")  # a UTF-8 byte-order mark is no value
    try:
        return data.decode("ascii")
    except UnicodeDecodeError:
        raise FormatError(path, "not a text file (non-ASCII bytes)") from None


def read_relations(path: str | Path, *, lenient: bool = False) -> Relations:
    """Read a benchmark relations file (plain text or gzip).

    Blank lines and lines starting with ``#`` are skipped. Every other line must hold exactly
    eight finite numbers ``t1 t2 x y z roll pitch yaw`` with ``|x|, |y| <= 1e6`` m
    (`scanguard.io.base.MAX_COORDINATE`), ``|t1|, |t2| <= 1e12`` s and angles within
    `MAX_RELATION_ANGLE`; a relation with
    ``t1 = t2`` must not move. A line repeated is counted once (with a warning). A UTF-8
    byte-order mark and any line ending are accepted.

    Args:
        path: The ``*.relations`` file (optionally gzipped).
        lenient: Skip lines that break these rules (one warning gives their count) instead
            of refusing the file.

    Returns:
        The relations, in file order.

    Raises:
        InputError: The file does not exist or cannot be read.
        FormatError: A line has the wrong number of values, a value that is not a number,
            not finite or out of bounds (the message names the file and line), or the file
            holds no relations.
    """
    p = Path(path)
    text = _read_text(p)
    rows: list[list[float]] = []
    skipped: list[str] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        problem = _line_problem(s.split())
        if isinstance(problem, str):
            if not lenient:
                raise FormatError(p, problem, location=f"line {lineno}")
            skipped.append(f"line {lineno}: {problem}")
            continue
        rows.append(problem)
    if skipped:
        warn_once(
            log,
            p,
            f"lenient read: skipped {len(skipped)} malformed line(s) (first: {skipped[0]})",
        )
    if not rows:
        raise FormatError(p, "no relations in file")
    data = _unique_rows(p, np.asarray(rows, dtype=np.float64))
    log.debug("%s: %d relations", p, len(data))
    return Relations(
        t1=data[:, 0].copy(),
        t2=data[:, 1].copy(),
        delta=np.ascontiguousarray(data[:, [2, 3, 7]]),
        path=str(p),
    )


def _unique_rows(path: Path, data: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rows with repeated lines kept once (first occurrence, file order), with a warning.

    A relation pasted twice is one measurement, not two: counting it again would weigh it
    in the error statistics as often as it was copied.
    """
    _, first = np.unique(data, axis=0, return_index=True)
    if first.size == data.shape[0]:
        return data
    warn_once(
        log,
        path,
        f"{data.shape[0] - first.size} repeated relation line(s); each relation counted once "
        f"({first.size} distinct)",
    )
    return data[np.sort(first)]


def _line_problem(tokens: list[str]) -> list[float] | str:
    """The values of one relation line, or what is wrong with it."""
    if len(tokens) != len(RELATION_COLUMNS):
        return (
            f"expected {len(RELATION_COLUMNS)} values ({' '.join(RELATION_COLUMNS)}), "
            f"found {len(tokens)}"
        )
    values: list[float] = []
    for name, tok in zip(RELATION_COLUMNS, tokens, strict=True):
        try:
            values.append(float(tok))
        except ValueError:
            return f"not a number for {name}: {printable(tok)!r}"
    bad = [name for name, v in zip(RELATION_COLUMNS, values, strict=True) if not np.isfinite(v)]
    if bad:
        return f"non-finite value for {', '.join(bad)}"
    far = [
        n
        for n, v in zip(RELATION_COLUMNS[2:4], values[2:4], strict=True)
        if abs(v) > MAX_COORDINATE
    ]
    if far:
        return f"{', '.join(far)} beyond +-{MAX_COORDINATE:.0e} m"
    late = [n for n, v in zip(RELATION_COLUMNS[:2], values[:2], strict=True) if abs(v) > MAX_STAMP]
    if late:
        return f"{', '.join(late)} beyond +-{MAX_STAMP:.0e} s"
    turned = [
        n
        for n, v in zip(RELATION_COLUMNS[5:], values[5:], strict=True)
        if abs(v) > MAX_RELATION_ANGLE
    ]
    if turned:  # 1e300 rad is no rotation anyone measured: refuse it, never wrap it
        return f"{', '.join(turned)} beyond +-{MAX_RELATION_ANGLE:g} rad"
    if values[0] == values[1] and max(abs(v) for v in values[2:]) > SAME_TIME_MOTION:
        return f"t1 = t2 = {values[0]:.6f} s but the relation moves (no motion takes no time)"
    return values
