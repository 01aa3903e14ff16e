"""CARMEN log reader (plain text or gzip): ``FLASER``, ``RLASER``, ``ROBOTLASER1`` and ``ODOM``.

Line formats (one message per line, space separated)::

    FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_ts
    RLASER (same as FLASER, rear laser)
    ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r_1 .. r_n
        n_rem rem_1 .. rem_k laser_x laser_y laser_theta robot_x robot_y robot_theta
        tv rv forward_safety side_safety turn_axis ipc_timestamp ipc_hostname logger_ts
    ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_ts

Conventions chosen here (documented because the old formats do not carry them):

* ``FLASER``/``RLASER`` cover 180 degrees with both ends included: ``angle_min = -pi/2`` and
  ``angle_increment = pi / (n - 1)``, so 181 beams are 1-degree steps and 180 or 360 beams
  still span exactly 180 degrees (what the public corrected logs need: their first and last
  beams look along the +-y axes).
* Ranges at or above the maximum range are "no return" codes (SICK: 81.83 / 81.91 m) and
  become ``+inf`` (ROS REP 117). The maximum is 80 m (SICK LMS long-range mode) unless the
  log clips all its no-returns to a smaller value (ACES: 50 m), which is detected as a pile-up
  of identical largest readings; ``CarmenReader(max_range=...)`` overrides both.
  ``ROBOTLASER1`` lines carry their maximum range and angles themselves.
* Corrected logs (``corrected=True``; by default: the file name contains ``corrected``, or
  the log holds ``NEFF`` lines, which GMapping writes into the corrected logs it outputs
  and no raw recording has): the pose in each laser line is the SLAM-corrected pose and
  becomes the reference (``"corrected_log"``). ``corrected=False`` reads such a log as raw.
  Their ``ODOM`` lines come from the raw recording and are **not** aligned with those poses
  (different start, frame and drift), and the odometry fields inside the laser lines are
  overwritten with the corrected pose; neither is exposed as odometry unless asked for
  (``odom_topic="ODOM"`` or ``"laser"``), because a detector trained on them would learn
  from wrong or leaked motion priors.
* Raw logs: the odometry fields of the laser lines become the odometry, no reference.
* The pose in ``FLASER`` lines is taken as the robot pose with the laser at the robot
  origin (``robot_frontlaser_offset`` is recorded in the metadata; it is 0 to 4 cm in the
  public logs). ``RLASER`` faces backwards (laser offset ``(0, 0, pi)``). ``ROBOTLASER1``
  gives both poses, so the laser offset is derived from them.

Strict parsing (hostile or damaged input never turns into silent garbage):

* every ``FLASER``/``RLASER`` line holds exactly ``n + 11`` fields and every ``ROBOTLASER1``
  line exactly the fields its beam and remission counts imply; ``ODOM`` lines hold 10;
* poses and odometry in laser lines must be finite with ``|x|, |y| <= 1e6`` m
  (`scanguard.io.base.MAX_COORDINATE`), stamps finite with ``|t| <= 1e12`` s, and the scan
  geometry valid (field of view in ``(0, 360]`` degrees);
* a line breaking a rule is an error naming the file and line. With ``lenient=True`` such
  lines are skipped instead, and one warning gives their count (and the first problem);
  ``ODOM`` values are parsed (and checked) only when ODOM lines are used;
* a file that is binary (a ROS bag, MCAP, SQLite, anything with NUL bytes at the start) is
  "not a CARMEN log"; a file named ``.gz`` without the gzip magic bytes is read as plain
  text with a warning (and a gzip file with another name is decompressed). Names of
  unknown line types are echoed only sanitised and bounded (`scanguard.io.base.printable`).
"""

from __future__ import annotations

import io
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, ScanError
from scanguard.geometry import relative, wrap_angle
from scanguard.io.base import (
    LENIENT_HINT,
    MAX_NAMES,
    align_poses,
    bad_pose_rows,
    bad_stamps,
    describe_counts,
    pose_problem,
    printable,
    read_file_bytes,
    stamp_problem,
    warn_once,
)
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

log = logging.getLogger(__name__)

__all__ = ["LASER_MESSAGES", "TOPIC_MESSAGES", "CarmenReader", "read_carmen_text"]

LASER_MESSAGES = ("ROBOTLASER1", "FLASER", "RLASER")
"""Laser message types, in the order the reader prefers them when several are present."""

TOPIC_MESSAGES = (*LASER_MESSAGES, "ODOM")
"""Message types the reader understands as data streams (``topics`` in the metadata); other
line types (``PARAM``, ``NEFF``, ``SYNC``...) are listed as ``other_lines``."""

CARMEN_MESSAGES = frozenset({*TOPIC_MESSAGES, "PARAM", "NEFF", "SYNC", "TRUEPOS"})
"""Line types whose presence marks a text file as a CARMEN log."""

SICK_MAX_RANGE = 80.0
CARMEN_RANGE_MIN = 0.01  # CARMEN has no minimum; a 0 reading is a failed return, not an obstacle
FLASER_FIELDS = 11  # name, n, 6 pose values, ipc timestamp, host, logger timestamp (+ n ranges)
ODOM_FIELDS = 10  # ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_timestamp
_SNIFF = 4096  # bytes looked at to tell text from binary
_INTEGER = re.compile(r"[+-]?[0-9]{1,12}")  # a count; longer ones are garbage (no big ints)

_BINARY_MAGIC = (
    (b"#ROSBAG", "a ROS 1 bag"),
    (b"\x89MCAP", "an MCAP file"),
    (b"SQLite format 3\x00", "an SQLite database (ROS 2 .db3)"),
    (b"\x89HDF", "an HDF5 file"),
    (b"PK\x03\x04", "a zip archive"),
    (b"BZh", "a bzip2 file"),
    (b"\xfd7zXZ", "an xz file"),
)


def read_carmen_text(path: Path) -> str:
    """Return the text of a CARMEN log, gunzipping it when it starts with the gzip magic.

    Compression is told by the magic bytes, not the name: a file named ``.gz`` that is not
    gzip-compressed is read as plain text, with a warning.

    Raises:
        InputError: The file does not exist or cannot be read.
        FormatError: The gzip stream is truncated or corrupt, or the file is binary (a ROS
            bag, MCAP, SQLite, NUL bytes...): "not a CARMEN log".
    """
    data = read_file_bytes(path, log, missing="file not found")
    _refuse_binary(path, data)
    try:
        return data.decode("ascii")
    except UnicodeDecodeError:
        # Host names in old logs are occasionally latin-1; numbers are ASCII either way.
        return data.decode("latin-1")


def _refuse_binary(path: Path, data: bytes) -> None:
    """Raise "not a CARMEN log" for a known binary format or NUL bytes at the start."""
    for magic, what in _BINARY_MAGIC:
        if data.startswith(magic):
            raise FormatError(path, f"not a CARMEN log (it is {what}; CARMEN logs are text)")
    if b"\x00" in data[:_SNIFF]:
        raise FormatError(path, "not a CARMEN log (binary data; CARMEN logs are text)")


@dataclass
class _Lines:
    """Parsed laser lines of one message type."""

    line_numbers: list[int]
    ranges: list[NDArray[np.float64]]
    tails: list[NDArray[np.float64]]  # per type: poses and stamp, see _parse_*
    geometry: list[tuple[float, float, float]]  # (angle_min, increment, max_range or nan)

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


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


@dataclass
class CarmenReader:
    """Reader for CARMEN logs (``.log``, ``.clf``, optionally gzipped).

    ``scan_topic`` selects the laser message type (``"FLASER"``, ``"RLASER"``,
    ``"ROBOTLASER1"``; default: the first present of ROBOTLASER1, FLASER, RLASER).
    ``odom_topic`` may be ``"ODOM"`` (ODOM lines, interpolated to the scans) or ``"laser"``
    (odometry fields of the laser lines). ``reference_topic`` may be ``"laser"`` (pose of the
    laser lines). See the module docstring for the defaults and why.

    Attributes:
        max_range: Override of the maximum range (m); readings at or above it become inf.
        corrected: Treat the log as SLAM-corrected (True) or raw (False); None decides from
            the file name (``corrected``) and the contents (``NEFF`` lines).
        lenient: Skip malformed lines (wrong count of values, garbled number, non-finite or
            absurd pose or stamp, invalid scan geometry) and count them, with one warning,
            instead of refusing the file.
    """

    max_range: float | None = None
    corrected: bool | None = None
    lenient: bool = False
    name: str = "carmen"
    extensions: tuple[str, ...] = (
        ".log",
        ".clf",
        ".carmen",
        ".log.gz",
        ".clf.gz",
        ".carmen.gz",
    )

    def read(
        self,
        path: Path,
        *,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        reference_topic: str | None = None,
    ) -> ScanSequence:
        """Read a CARMEN log into a `ScanSequence` (see the class docstring for topics).

        Raises:
            InputError: Missing file, no laser lines, unknown topic name.
            FormatError: Truncated gzip, binary file, garbled or truncated line, wrong count
                of values, non-finite or absurd pose or stamp, zero-beam scan, field of view
                outside (0, 360] degrees (the message names the file and line number).
        """
        path = Path(path)
        text = read_carmen_text(path)
        problems = _Problems(path, self.lenient)
        lasers: dict[str, _Lines] = {k: _Lines([], [], [], []) for k in LASER_MESSAGES}
        counts: dict[str, int] = {}
        others: dict[str, int] = {}
        odom_rows: list[list[str]] = []
        odom_lines: list[int] = []
        params: dict[str, str] = {}
        old_style: dict[str, list[tuple[int, str, bool]]] = {"FLASER": [], "RLASER": []}
        for lineno, line in enumerate(text.split("\n"), start=1):
            if not line or line[0] == "#":
                continue
            if line.startswith(("FLASER ", "RLASER ")):
                kind = line[:6]
                counts[kind] = counts.get(kind, 0) + 1
                old_style[kind].append((lineno, line, True))
                continue
            tokens = line.split()
            if not tokens:
                continue
            kind = tokens[0]
            if kind not in TOPIC_MESSAGES:
                others[kind] = others.get(kind, 0) + 1
                if kind == "PARAM" and len(tokens) >= 3:
                    params[tokens[1]] = tokens[2]
                continue
            counts[kind] = counts.get(kind, 0) + 1
            if kind in ("FLASER", "RLASER"):
                old_style[kind].append((lineno, line, False))
            elif kind == "ROBOTLASER1":
                try:
                    _parse_robotlaser(path, tokens, lineno, lasers[kind])
                except FormatError as exc:
                    problems.add(exc)
            elif len(tokens) != ODOM_FIELDS:  # ODOM
                problems.add(_count_error(path, kind, lineno, ODOM_FIELDS, len(tokens), ""))
            else:
                odom_rows.append(tokens[1:4] + tokens[7:8])
                odom_lines.append(lineno)

        for kind, raw_lines in old_style.items():
            if raw_lines:
                _parse_flaser_lines(path, raw_lines, lasers[kind], problems)
        for kind in LASER_MESSAGES:
            lasers[kind] = _check_tails(path, kind, lasers[kind], problems)
        present = [k for k in LASER_MESSAGES if lasers[k].ranges]
        if not present:
            self._no_laser(path, counts, others, problems)
        if scan_topic is None:
            kind = present[0]
            if len(present) > 1:
                log.info("%s: laser types %s present; using %s", path, present, kind)
        else:
            kind = scan_topic.upper()
            if kind not in present:
                raise InputError(
                    path,
                    f"no {printable(scan_topic)} lines; laser types present: {', '.join(present)}",
                    location=f"topic {printable(scan_topic)}",
                )
        data = lasers[kind]

        if kind == "ROBOTLASER1":
            max_range = self.max_range
            sensor_name = "CARMEN ROBOTLASER1"
        else:
            max_range = self.max_range if self.max_range is not None else _clip_code(data.ranges)
            sensor_name = f"SICK LMS (CARMEN {kind})"
        scans: list[LaserScan] = []
        kept: list[int] = []
        for i, (lineno, r, (amin, inc, mr)) in enumerate(
            zip(data.line_numbers, data.ranges, data.geometry, strict=True)
        ):
            limit = max_range if max_range is not None else mr
            with np.errstate(over="ignore", invalid="ignore"):
                r32 = np.where(r >= limit, np.inf, r).astype(np.float32)
            try:
                scan = LaserScan(
                    stamp=float(data.tails[i][6]),
                    ranges=r32,
                    angle_min=amin,
                    angle_increment=inc,
                    range_min=CARMEN_RANGE_MIN,
                    range_max=float(limit),
                )
            except ScanError as exc:
                problems.add(FormatError(path, f"{kind}: {exc}", location=f"line {lineno}"))
                continue
            scans.append(scan)
            kept.append(i)
        if not scans:
            self._no_laser(path, counts, others, problems)
        if len(kept) < len(data.tails):
            data = data.keep(np.isin(np.arange(len(data.tails)), kept))

        # ipc_timestamp: when the laser message was sent (the logger stamp adds queueing).
        tails = np.stack(data.tails)
        pose, embedded_odom, stamps = tails[:, 0:3], tails[:, 3:6], tails[:, 6].copy()
        pose[:, 2] = wrap_angle(pose[:, 2])
        embedded_odom[:, 2] = wrap_angle(embedded_odom[:, 2])

        s0 = scans[0]
        diffs = np.diff(stamps)
        pos = diffs[diffs > 0]
        rate = float(1.0 / np.median(pos)) if pos.size > diffs.size // 2 else None
        sensor = SensorInfo(
            name=sensor_name,
            n_beams=s0.n_beams,
            angle_min=s0.angle_min,
            angle_increment=s0.angle_increment,
            range_min=s0.range_min,
            range_max=s0.range_max,
            rate_hz=rate,
        )
        ranked = sorted(others.items(), key=lambda kv: (-kv[1], kv[0]))
        other_lines = {printable(k): v for k, v in ranked[:MAX_NAMES]}
        if len(ranked) > MAX_NAMES:
            rest = ranked[MAX_NAMES:]
            other_lines[f"({len(rest)} more kinds)"] = sum(v for _, v in rest)
        metadata: dict[str, Any] = {
            "format": self.name,
            "source": str(path),
            "path": str(path),
            "scan_topic": kind,
            "topics": {k: {"type": f"carmen/{k}", "count": v} for k, v in sorted(counts.items())},
            "other_lines": other_lines,
        }
        for key in ("robot_frontlaser_offset", "robot_rearlaser_offset"):
            if key in params:
                metadata[f"carmen_{key}"] = printable(params[key])

        n_distinct = int(np.unique(stamps).size)
        if diffs.size and n_distinct < 0.5 * stamps.size:
            note = (
                f"only {_plural(n_distinct, 'distinct stamp')} for {stamps.size} scans "
                "(the log stores rounded times)"
            )
            metadata["stamps_unreliable"] = note
            warn_once(log, path, f"{note}; rate and duration are unknown")
        elif diffs.size and np.any(diffs <= 0):
            bad = int((diffs <= 0).sum())
            metadata["stamps_not_increasing"] = bad
            warn_once(
                log,
                path,
                f"{bad} of {diffs.size} consecutive laser stamps do not increase (largest step "
                f"back {float(-diffs.min()):.3f} s); kept in file order",
            )

        corrected = self.corrected
        by = "option"
        if corrected is None:
            if "corrected" in path.name.lower():
                corrected, by = True, "file name"
            elif others.get("NEFF", 0) > 0:
                corrected, by = True, "NEFF lines"
                log.info(
                    "%s: read as a SLAM-corrected log (it holds NEFF lines, which GMapping "
                    "writes into corrected logs): its poses are the reference; "
                    "corrected=False reads it as raw",
                    path,
                )
            else:
                corrected, by = False, "no NEFF lines, no 'corrected' in the name"
        metadata["carmen_corrected"] = corrected
        metadata["carmen_corrected_by"] = by

        laser_offset = np.zeros(3)
        if kind == "RLASER":
            laser_offset = np.array([0.0, 0.0, np.pi])
        elif kind == "ROBOTLASER1":
            laser_offset = relative(pose[0], embedded_odom[0])
            # robot pose and laser pose share the slots of FLASER's (pose, odom): the
            # second one is the laser, not odometry, for this message type.
            embedded_odom = pose.copy()

        reference: NDArray[np.float64] | None = None
        reference_kind: str | None = None
        ref_choice = reference_topic
        if ref_choice is None:
            ref_choice = "laser" if corrected else None
        if ref_choice is not None:
            if ref_choice.lower() not in ("laser", kind.lower()):
                raise InputError(
                    path,
                    f"unknown reference source {printable(ref_choice)!r} for a CARMEN log "
                    "(use 'laser')",
                    location=f"topic {printable(ref_choice)}",
                )
            reference = pose.copy()
            reference_kind = "corrected_log" if corrected else "log_pose"
            metadata["reference_source"] = f"{kind} pose"
        else:
            metadata["reference_hint"] = (
                "if the poses of this CARMEN log are SLAM-corrected, read it as a corrected "
                "log (corrected=True, CLI --corrected): its poses become the reference"
            )

        odometry: NDArray[np.float64] | None = None
        odom_choice = odom_topic
        if odom_choice is None:
            odom_choice = None if corrected else "laser"
        if odom_choice is not None:
            if odom_choice.upper() == "ODOM":
                odometry = self._odom_lines(
                    path, odom_rows, odom_lines, stamps, metadata, corrected, problems
                )
                metadata["odometry_source"] = "ODOM lines"
            elif odom_choice.lower() in ("laser", kind.lower()):
                odometry = embedded_odom
                metadata["odometry_source"] = f"{kind} odometry fields"
            else:
                raise InputError(
                    path,
                    f"unknown odometry source {printable(odom_choice)!r} for a CARMEN log "
                    "(use 'ODOM' or 'laser')",
                    location=f"topic {printable(odom_choice)}",
                )
        elif odom_rows:
            if "stamps_unreliable" in metadata:
                metadata["odometry_hint"] = (
                    f"the log has {len(odom_rows)} ODOM lines, but its rounded stamps cannot "
                    "align them with the scans"
                )
            else:
                metadata["odometry_hint"] = (
                    f"not used by default: the log has {len(odom_rows)} ODOM lines (raw "
                    "odometry, not aligned with the corrected poses); --odom-topic ODOM "
                    "uses them"
                )

        if problems.count:
            metadata["skipped_lines"] = problems.count
            warn_once(
                log,
                path,
                f"lenient read: skipped {_plural(problems.count, 'malformed line')} "
                f"(first: {problems.first})",
            )

        name = path.name
        for suffix in sorted(self.extensions, key=len, reverse=True):
            if name.lower().endswith(suffix):
                name = name[: -len(suffix)]
                break
        log.debug("%s: %d %s scans", path, len(scans), kind)
        try:
            return ScanSequence(
                name=name,
                scans=scans,
                sensor=sensor,
                odometry=odometry,
                reference=reference,
                reference_kind=reference_kind,
                laser_offset=laser_offset,
                metadata=metadata,
            )
        except ScanError as exc:  # pragma: no cover - the checks above come first
            raise FormatError(path, str(exc)) from None

    @staticmethod
    def _no_laser(
        path: Path, counts: dict[str, int], others: dict[str, int], problems: _Problems
    ) -> None:
        """Raise the error for a log without (usable) laser lines."""
        if problems.count:
            raise FormatError(
                path,
                f"no usable laser lines: {_plural(problems.count, 'malformed line')} skipped "
                f"(first: {problems.first})",
            )
        if not (set(counts) | set(others)) & CARMEN_MESSAGES:
            raise FormatError(
                path,
                "not a CARMEN log (no FLASER, RLASER, ROBOTLASER1 or ODOM lines); "
                f"first words of its lines: {describe_counts(others)}",
            )
        found = describe_counts(counts) if counts else "no data lines"
        if others:
            found += f"; other lines: {describe_counts(others)}"
        raise InputError(
            path, f"no laser lines (FLASER, RLASER or ROBOTLASER1) in the log; found {found}"
        )

    @staticmethod
    def _odom_lines(
        path: Path,
        rows: list[list[str]],
        line_numbers: list[int],
        stamps: NDArray[np.float64],
        metadata: dict[str, Any],
        corrected: bool,
        problems: _Problems,
    ) -> NDArray[np.float64]:
        """ODOM lines interpolated to the scan stamps (checked: numbers, finite, bounded)."""
        if not rows:
            raise InputError(path, "no ODOM lines in the log", location="topic ODOM")
        if "stamps_unreliable" in metadata:
            raise InputError(
                path,
                "cannot align ODOM lines with laser lines: the log's stamps are rounded",
                location="topic ODOM",
            )
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
        if od.size == 0:
            raise FormatError(path, "no usable ODOM lines", location="topic ODOM")
        if corrected:
            warn_once(log, path, "ODOM lines of a corrected log are not aligned with its scans")
        return align_poses(path, "ODOM lines", od[:, 3], od[:, :3], stamps)
