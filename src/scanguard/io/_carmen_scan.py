"""One pass over a CARMEN log's lines (`scanguard.io.carmen`): sorted by type, lasers parsed.

`_Limit` stops the pass after ``max_scans`` laser lines (`CarmenReader.max_scans`).
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from pathlib import Path

from scanguard.errors import FormatError
from scanguard.io._carmen_lines import (
    _check_tails,
    _count_error,
    _Lines,
    _parse_flaser_lines,
    _parse_robotlaser,
    _Problems,
)
from scanguard.io.base import warn_once

log = logging.getLogger("scanguard.io.carmen")  # the reader's warnings, under its name

LASER_MESSAGES = ("ROBOTLASER1", "FLASER", "RLASER")
"""Laser message types, in the order the reader prefers them when several are present."""

TOPIC_MESSAGES = (*LASER_MESSAGES, "ODOM")
"""Message types the reader understands as data streams (``topics`` in the metadata); other
line types (``PARAM``, ``NEFF``, ``SYNC``...) are listed as ``other_lines``."""

CARMEN_MESSAGES = frozenset({*TOPIC_MESSAGES, "PARAM", "NEFF", "SYNC", "TRUEPOS"})
"""Line types whose presence marks a text file as a CARMEN log."""

CARMEN_RANGE_MIN = 0.01  # CARMEN has no minimum; a 0 reading is a failed return, not an obstacle
ODOM_FIELDS = 10  # ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_timestamp


@dataclass
class _Log:
    """What one pass over a log's lines found."""

    lasers: dict[str, _Lines]
    counts: dict[str, int] = field(default_factory=dict)  # data lines per type
    others: dict[str, int] = field(default_factory=dict)  # other lines per first word
    odom_rows: list[list[str]] = field(default_factory=list)  # x, y, theta, ipc stamp
    odom_lines: list[int] = field(default_factory=list)
    params: dict[str, str] = field(default_factory=dict)


class _Limit:
    """Where a read cut to ``max_scans`` laser lines stops (see `CarmenReader.max_scans`).

    Reading stops once every laser type seen (or the one asked for) has ``max_scans`` lines
    and, when the log has ODOM lines, one ODOM line is stamped at or after the last laser line
    kept: ODOM poses are interpolated to the scan stamps, so later ones change nothing.
    """

    def __init__(self, max_scans: int, kind: str | None) -> None:
        self.max_scans = max_scans
        self.kind = None if kind is None else kind.upper()  # the laser type asked for
        self.last_stamp: float | None = None  # of the last laser line kept, once full
        self.stopped = False

    def full(self, counts: dict[str, int]) -> bool:
        """Whether the laser lines asked for are all in."""
        if self.kind is not None:
            return counts.get(self.kind, 0) >= self.max_scans
        seen = [counts.get(k, 0) for k in LASER_MESSAGES if counts.get(k, 0)]
        return bool(seen) and min(seen) >= self.max_scans

    def note_laser(self, line: str, counts: dict[str, int]) -> None:
        """After a laser line was counted: remember its stamp once the lasers are full."""
        if self.last_stamp is None and self.full(counts):
            self.last_stamp = _tail_stamp(line)

    def done(self, tokens: list[str]) -> bool:
        """Whether an ODOM line (its ``tokens``) is stamped at or after the last scan kept."""
        if self.last_stamp is None or len(tokens) != ODOM_FIELDS:
            return False
        try:
            return float(tokens[7]) >= self.last_stamp
        except ValueError:
            return False

    def after(self, line: str, lineno: int, found: _Log) -> str:
        """Once the lasers are full: ``"stop"``, ``"skip"`` the line or ``"read"`` it."""
        tokens = line.split() if line.startswith("ODOM ") else []
        if not found.odom_rows or self.done(tokens):
            self.stopped = True
            if tokens:  # the ODOM line past the last scan bounds its interpolation
                found.odom_rows.append(tokens[1:4] + tokens[7:8])
                found.odom_lines.append(lineno)
                found.counts["ODOM"] = found.counts.get("ODOM", 0) + 1
            return "stop"
        return "read" if tokens else "skip"  # past the limit only ODOM lines are wanted


def _tail_stamp(line: str) -> float:
    """The ipc stamp of a laser line (third field from the end; -inf if garbled)."""
    try:
        return float(line.split()[-3])
    except (IndexError, ValueError):
        return float("-inf")


def _scan_log(path: Path, text: str, problems: _Problems, limit: _Limit | None = None) -> _Log:
    """Sort the lines by type and parse the laser lines (checked; see the module docstring).

    With ``limit``, laser lines past it are not read, and reading stops where it says.
    """
    found = _Log({k: _Lines([], [], [], []) for k in LASER_MESSAGES})
    lasers, counts, others = found.lasers, found.counts, found.others
    old_style: dict[str, list[tuple[int, str, bool]]] = {"FLASER": [], "RLASER": []}
    for lineno, line in enumerate(io.StringIO(text), start=1):
        line = line.rstrip("\n")
        if not line or line[0] == "#":
            continue
        if limit is not None and limit.last_stamp is not None:
            what = limit.after(line, lineno, found)
            if what == "stop":
                break
            if what == "skip":
                continue
        if line.startswith(("FLASER ", "RLASER ")):
            kind = line[:6]
            counts[kind] = counts.get(kind, 0) + 1
            old_style[kind].append((lineno, line, True))
            if limit is not None:
                limit.note_laser(line, counts)
            continue
        tokens = line.split()
        if not tokens:
            continue
        kind = tokens[0]
        if kind not in TOPIC_MESSAGES:
            others[kind] = others.get(kind, 0) + 1
            if kind == "PARAM" and len(tokens) >= 3:
                found.params[tokens[1]] = tokens[2]
            continue
        counts[kind] = counts.get(kind, 0) + 1
        if kind in ("FLASER", "RLASER"):
            old_style[kind].append((lineno, line, False))
        elif kind == "ROBOTLASER1":
            try:
                _parse_robotlaser(path, tokens, lineno, lasers[kind])
            except FormatError as exc:
                problems.add(exc)
            if limit is not None:
                limit.note_laser(line, counts)
        elif len(tokens) != ODOM_FIELDS:  # ODOM
            problems.add(_count_error(path, kind, lineno, ODOM_FIELDS, len(tokens), ""))
        else:
            found.odom_rows.append(tokens[1:4] + tokens[7:8])
            found.odom_lines.append(lineno)

    for kind, raw_lines in old_style.items():
        if raw_lines:
            _parse_flaser_lines(path, raw_lines, lasers[kind], problems)
    mismatch = lasers["ROBOTLASER1"].fov_mismatch
    if mismatch:
        warn_once(
            log,
            path,
            f"{len(mismatch)} ROBOTLASER1 line(s) state a field of view that is not beams x "
            f"resolution (first: line {mismatch[0]}); the resolution is used",
        )
    for kind in LASER_MESSAGES:
        lasers[kind] = _check_tails(path, kind, lasers[kind], problems)
    return found
