"""Line parsers of the CARMEN reader (`scanguard.io.carmen`): laser lines to numbers.

Every parser checks its line strictly and raises `FormatError` naming the file and line;
`_Problems` turns those into errors (strict) or counted skips (lenient).
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError
from scanguard.geometry import wrap_angle
from scanguard.io.base import (
    LENIENT_HINT,
    bad_pose_rows,
    bad_stamps,
    pose_problem,
    printable,
    stamp_problem,
)

SICK_MAX_RANGE = 80.0
FLASER_FIELDS = 11  # name, n, 6 pose values, ipc timestamp, host, logger timestamp (+ n ranges)
_INTEGER = re.compile(r"[+-]?[0-9]{1,12}")  # a count; longer ones are garbage (no big ints)


@dataclass
class _Lines:
    """Parsed laser lines of one message type."""

    line_numbers: list[int]
    ranges: list[NDArray[np.float64]]
    tails: list[NDArray[np.float64]]  # per type: poses and stamp, see _parse_*
    geometry: list[tuple[float, float, float]]  # (angle_min, increment, max_range or nan)
    # ROBOTLASER1 lines whose stated field of view is not beams x resolution
    fov_mismatch: list[int] = field(default_factory=list)

    def keep(self, mask: NDArray[np.bool_]) -> _Lines:
        """The lines where ``mask`` is true."""
        idx = np.flatnonzero(mask)
        return _Lines(
            [self.line_numbers[i] for i in idx],
            [self.ranges[i] for i in idx],
            [self.tails[i] for i in idx],
            [self.geometry[i] for i in idx],
        )


class _Problems:
    """Malformed lines: raised at once (strict) or skipped and counted (lenient)."""

    def __init__(self, path: Path, lenient: bool) -> None:
        self.path = path
        self.lenient = lenient
        self.count = 0
        self.first: str | None = None

    def add(self, exc: FormatError) -> None:
        """Raise ``exc`` (strict, with a hint about lenient reads) or count it (lenient)."""
        if not self.lenient:
            raise FormatError(exc.path, exc.problem + LENIENT_HINT, location=exc.location)
        self.count += 1
        if self.first is None:
            self.first = f"{exc.location}: {exc.problem}" if exc.location else exc.problem


def _numbers(path: Path, tokens: list[str], lineno: int, kind: str) -> NDArray[np.float64]:
    try:
        return np.array(tokens, dtype=np.float64)
    except ValueError:
        for tok in tokens:
            try:
                float(tok)
            except ValueError:
                raise FormatError(
                    path, f"{kind}: {printable(tok)!r} is not a number", location=f"line {lineno}"
                ) from None
        raise  # pragma: no cover - one token above always fails


def _count_error(
    path: Path, kind: str, lineno: int, need: int, have: int, what: str
) -> FormatError:
    expected = f"expected {need} {what}".rstrip()
    if have < need:
        problem = f"{kind}: truncated line ({have} fields, {expected})"
    else:
        problem = f"{kind}: {have - need} extra values ({have} fields, {expected})"
    return FormatError(path, problem, location=f"line {lineno}")


def _count(path: Path, tokens: list[str], idx: int, lineno: int, kind: str, what: str) -> int:
    """Integer field ``tokens[idx]`` (a beam or remission count)."""
    got = tokens[idx] if idx < len(tokens) else None
    if got is None or not _INTEGER.fullmatch(got):
        shown = "nothing" if got is None else repr(printable(got))
        raise FormatError(
            path, f"{kind}: {what} must be an integer, got {shown}", location=f"line {lineno}"
        )
    return int(got)


def _beam_count(path: Path, tokens: list[str], idx: int, lineno: int, kind: str) -> int:
    n = _count(path, tokens, idx, lineno, kind, "beam count")
    if n <= 0:
        raise FormatError(
            path, f"{kind}: scan has {n} beams (zero-beam scan)", location=f"line {lineno}"
        )
    return n


_Parsed = tuple[NDArray[np.float64], NDArray[np.float64], tuple[float, float, float]]


def _parse_flaser(path: Path, tokens: list[str], lineno: int) -> _Parsed:
    kind = tokens[0]
    if len(tokens) < 2:
        raise FormatError(
            path, f"{kind}: truncated line (no beam count)", location=f"line {lineno}"
        )
    n = _beam_count(path, tokens, 1, lineno, kind)
    need = n + FLASER_FIELDS
    if len(tokens) != need:
        raise _count_error(path, kind, lineno, need, len(tokens), f"for {n} beams")
    vals = _numbers(path, tokens[2 : n + 9], lineno, kind)  # ranges, 6 pose values, ipc stamp
    # tail: robot pose (3), odometry pose (3), stamp
    return vals[:n], vals[n:], (-np.pi / 2, np.pi / (n - 1) if n > 1 else np.pi, np.nan)


def _parse_flaser_lines(
    path: Path, lines: list[tuple[int, str, bool]], out: _Lines, problems: _Problems
) -> None:
    """Parse FLASER/RLASER lines with numpy's C text parser; per line where that fails."""
    # Each line holds "NAME n r_1..r_n x y th ox oy oth ipc_ts host logger_ts": dropping
    # the name and the last two tokens leaves n + 8 numbers. Lines are grouped by n so that
    # every group is a rectangular table for np.loadtxt (far faster than float() per token).
    # A group that does not parse as exactly n + 8 numbers per line is parsed line by line,
    # which names the offending line (wrong count, garbled number...).
    groups: dict[int, list[int]] = {}
    bodies: list[str] = []
    slow: list[int] = []
    for i, (_, line, plain) in enumerate(lines):
        parts = line[7:].rsplit(maxsplit=2) if plain else []
        bodies.append(parts[0] if len(parts) == 3 else "")
        n_text = parts[0].split(maxsplit=1)[0] if len(parts) == 3 else ""
        if not (n_text.isascii() and n_text.isdigit()) or len(n_text) > 9 or int(n_text) < 2:
            slow.append(i)
            continue
        groups.setdefault(int(n_text), []).append(i)
    parsed: list[_Parsed | None] = [None] * len(lines)
    for n, idx in groups.items():
        try:
            table = np.loadtxt(
                io.StringIO("\n".join(bodies[i] for i in idx)),
                dtype=np.float64,
                comments=None,
                ndmin=2,
            )
        except ValueError:
            table = None
        if table is None or table.shape != (len(idx), n + 8):
            slow.extend(idx)
            continue
        geometry = (-np.pi / 2, np.pi / (n - 1), np.nan)
        for i, row in zip(idx, table, strict=True):
            parsed[i] = (row[1 : n + 1], row[n + 1 : n + 8], geometry)
    for i in sorted(slow):
        lineno, line, _ = lines[i]
        try:
            parsed[i] = _parse_flaser(path, line.split(), lineno)
        except FormatError as exc:
            problems.add(exc)
    for (lineno, _, _), item in zip(lines, parsed, strict=True):
        if item is not None:
            out.line_numbers.append(lineno)
            out.ranges.append(item[0])
            out.tails.append(item[1])
            out.geometry.append(item[2])


def _parse_robotlaser(path: Path, tokens: list[str], lineno: int, out: _Lines) -> None:
    kind = tokens[0]
    if len(tokens) < 10:
        raise _count_error(path, kind, lineno, 10, len(tokens), "or more")
    n = _beam_count(path, tokens, 8, lineno, kind)
    if len(tokens) < 10 + n:
        raise _count_error(path, kind, lineno, 10 + n, len(tokens), f"or more for {n} beams")
    n_rem = _count(path, tokens, 9 + n, lineno, kind, "remission count")
    if n_rem < 0:
        raise FormatError(
            path, f"{kind}: negative remission count {n_rem}", location=f"line {lineno}"
        )
    start = 10 + n + n_rem
    need = start + 12  # laser pose, robot pose, 5 velocities/safety values, timestamp
    if len(tokens) != need + 2:  # + ipc host name and logger timestamp
        raise _count_error(
            path, kind, lineno, need + 2, len(tokens), f"for {n} beams and {n_rem} remissions"
        )
    head = _numbers(path, tokens[2:6], lineno, kind)
    ranges = _numbers(path, tokens[9 : 9 + n], lineno, kind)
    tail = _numbers(path, tokens[start:need], lineno, kind)
    out.line_numbers.append(lineno)
    out.ranges.append(ranges)
    # tail: robot pose (3), laser pose (3), stamp -- same slots as FLASER's (pose, odom, stamp)
    out.tails.append(np.concatenate([tail[3:6], tail[0:3], tail[11:12]]))
    out.geometry.append((float(head[0]), float(head[2]), float(head[3])))
    fov, res = float(head[1]), float(head[2])
    # drivers state the span first to last beam, (n - 1) x res, or n x res: both are fine
    off = min(abs(fov - (n - 1) * res), abs(fov - n * res))
    if not off <= max(0.5 * abs(res), 1e-3):
        out.fov_mismatch.append(lineno)


def _check_tails(path: Path, kind: str, data: _Lines, problems: _Problems) -> _Lines:
    """Refuse (or, lenient, drop) lines with a non-finite or absurd pose or stamp."""
    if not data.tails:
        return data
    tails = np.stack(data.tails)
    bad_pose = bad_pose_rows(tails[:, 0:3])
    bad_second = bad_pose_rows(tails[:, 3:6])
    bad = bad_pose | bad_second | bad_stamps(tails[:, 6])
    if not bad.any():
        return data
    second = "laser pose" if kind == "ROBOTLASER1" else "odometry"
    for i in np.flatnonzero(bad):
        row = tails[i]
        if bad_pose[i]:
            problem = pose_problem(row[0:3], "pose")
        elif bad_second[i]:
            problem = pose_problem(row[3:6], second)
        else:
            problem = stamp_problem(float(row[6]))
        problems.add(
            FormatError(path, f"{kind}: {problem}", location=f"line {data.line_numbers[i]}")
        )
    return data.keep(~bad)


def _clip_code(ranges: list[NDArray[np.float64]]) -> float:
    """Maximum range of FLASER/RLASER data: 80 m unless no-returns pile up at a lower value."""
    allr = np.concatenate(ranges)
    finite = allr[np.isfinite(allr)]
    if finite.size == 0:
        return SICK_MAX_RANGE
    m = float(finite.max())
    if m >= SICK_MAX_RANGE:
        return SICK_MAX_RANGE
    # A clip value shows up as many identical readings at the very top; a real wall at the
    # largest distance of the whole log would not repeat exactly at cm resolution.
    pile = int((finite == m).sum())
    if pile >= max(5, int(0.001 * finite.size)):
        return m
    return SICK_MAX_RANGE


def _odom_table(
    path: Path, rows: list[list[str]], line_numbers: list[int], problems: _Problems
) -> NDArray[np.float64]:
    """ODOM rows (x, y, theta, stamp) as numbers, less the garbled or absurd ones."""
    try:
        od = np.array(rows, dtype=np.float64)
    except ValueError:
        od = np.full((len(rows), 4), np.nan)
        garbled = np.zeros(len(rows), dtype=bool)
        for k, (row, ln) in enumerate(zip(rows, line_numbers, strict=True)):
            try:
                od[k] = _numbers(path, row, ln, "ODOM")
            except FormatError as exc:
                problems.add(exc)  # lenient: counted here, dropped below
                garbled[k] = True
    else:
        garbled = np.zeros(len(rows), dtype=bool)
    bad = bad_pose_rows(od[:, :3]) | bad_stamps(od[:, 3])
    for k in map(int, np.flatnonzero(bad & ~garbled)):
        problem = (
            pose_problem(od[k, :3], "odometry")
            if bad_pose_rows(od[k, :3])[0]
            else stamp_problem(float(od[k, 3]))
        )
        problems.add(FormatError(path, f"ODOM: {problem}", location=f"line {line_numbers[k]}"))
    od = od[~bad]
    # huge headings (finite but absurd) would overflow np.unwrap in the interpolation;
    # ordinary ones are left as they are (wrapping them all changes bits of real logs)
    big = np.abs(od[:, 2]) > 1e3
    od[big, 2] = wrap_angle(od[big, 2])
    return od
