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
* Corrected logs (file name contains ``corrected``, or ``corrected=True``): the pose in each
  laser line is the SLAM-corrected pose and becomes the reference (``"corrected_log"``).
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
"""

from __future__ import annotations

import gzip
import io
import logging
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, ScanError
from scanguard.geometry import relative, wrap_angle
from scanguard.io.base import align_poses
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

log = logging.getLogger(__name__)

__all__ = ["LASER_MESSAGES", "CarmenReader", "read_carmen_text"]

LASER_MESSAGES = ("ROBOTLASER1", "FLASER", "RLASER")
"""Laser message types, in the order the reader prefers them when several are present."""

SICK_MAX_RANGE = 80.0
CARMEN_RANGE_MIN = 0.01  # CARMEN has no minimum; a 0 reading is a failed return, not an obstacle


def read_carmen_text(path: Path) -> str:
    """Return the text of a CARMEN log, gunzipping it when it starts with the gzip magic.

    Raises:
        InputError: The file does not exist or cannot be read.
        FormatError: The gzip stream is truncated or corrupt, or the text is not decodable.
    """
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        with path.open("rb") as fh:
            magic = fh.read(2)
        if magic == b"\x1f\x8b":
            with gzip.open(path, "rb") as gz:
                data = gz.read()
        else:
            data = path.read_bytes()
    except EOFError:
        raise FormatError(path, "truncated gzip file (compressed stream ends early)") from None
    except (gzip.BadGzipFile, zlib.error) as exc:
        raise FormatError(path, f"corrupt gzip file ({exc})") from None
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    try:
        return data.decode("ascii")
    except UnicodeDecodeError:
        # Host names in old logs are occasionally latin-1; numbers are ASCII either way.
        return data.decode("latin-1")


@dataclass
class _Lines:
    """Parsed laser lines of one message type."""

    line_numbers: list[int]
    ranges: list[NDArray[np.float64]]
    tails: list[NDArray[np.float64]]  # per type: poses and stamp, see _parse_*
    geometry: list[tuple[float, float, float]]  # (angle_min, increment, max_range or nan)


def _numbers(path: Path, tokens: list[str], lineno: int, kind: str) -> NDArray[np.float64]:
    try:
        return np.array(tokens, dtype=np.float64)
    except ValueError:
        for tok in tokens:
            try:
                float(tok)
            except ValueError:
                raise FormatError(
                    path, f"{kind}: {tok!r} is not a number", location=f"line {lineno}"
                ) from None
        raise  # pragma: no cover - one token above always fails


def _too_short(path: Path, kind: str, lineno: int, need: int, have: int) -> FormatError:
    return FormatError(
        path,
        f"{kind}: truncated line ({have} fields, expected at least {need})",
        location=f"line {lineno}",
    )


def _beam_count(path: Path, tokens: list[str], idx: int, lineno: int, kind: str) -> int:
    try:
        n = int(tokens[idx])
    except (ValueError, IndexError):
        got = tokens[idx] if idx < len(tokens) else "nothing"
        raise FormatError(
            path, f"{kind}: beam count must be an integer, got {got!r}", location=f"line {lineno}"
        ) from None
    if n <= 0:
        raise FormatError(
            path, f"{kind}: scan has {n} beams (zero-beam scan)", location=f"line {lineno}"
        )
    return n


def _parse_flaser(path: Path, tokens: list[str], lineno: int, out: _Lines) -> None:
    kind = tokens[0]
    n = _beam_count(path, tokens, 1, lineno, kind)
    need = n + 9  # name, n, ranges, 6 pose values, ipc timestamp
    if len(tokens) < need:
        raise _too_short(path, kind, lineno, need + 2, len(tokens))
    vals = _numbers(path, tokens[2:need], lineno, kind)
    out.line_numbers.append(lineno)
    out.ranges.append(vals[:n])
    # tail: robot pose (3), odometry pose (3), stamp
    out.tails.append(vals[n:])
    out.geometry.append((-np.pi / 2, np.pi / (n - 1) if n > 1 else np.pi, np.nan))


def _parse_flaser_lines(path: Path, lines: list[tuple[int, str]], out: _Lines) -> None:
    """Parse FLASER/RLASER lines with numpy's C text parser; per line only if that fails."""
    # Each line holds "NAME n r_1..r_n x y th ox oy oth ipc_ts host logger_ts": dropping
    # the name and the last two tokens leaves n + 8 numbers. Lines are grouped by n so that
    # every group is a rectangular table for np.loadtxt (far faster than float() per token).
    groups: dict[str, list[int]] = {}
    bodies: list[str] = []
    for i, (_, line) in enumerate(lines):
        body = line[7:].rsplit(maxsplit=2)[0]
        bodies.append(body)
        groups.setdefault(body.split(maxsplit=1)[0], []).append(i)
    rows: dict[int, NDArray[np.float64]] = {}
    try:
        for n_text, idx in groups.items():
            n = int(n_text)
            if n < 2:
                raise ValueError(n_text)
            table = np.loadtxt(
                io.StringIO("\n".join(bodies[i] for i in idx)),
                dtype=np.float64,
                comments=None,
                ndmin=2,
            )
            if table.shape != (len(idx), n + 8):
                raise ValueError(n_text)
            for i, row in zip(idx, table, strict=True):
                rows[i] = row
    except ValueError:
        # Slow path: find and name the offending line (garbled number, truncated line...).
        for lineno, line in lines:
            _parse_flaser(path, line.split(), lineno, out)
        return
    for i, (lineno, _) in enumerate(lines):
        row = rows[i]
        n = int(row[0])
        out.line_numbers.append(lineno)
        out.ranges.append(row[1 : n + 1])
        out.tails.append(row[n + 1 : n + 8])
        out.geometry.append((-np.pi / 2, np.pi / (n - 1), np.nan))


def _parse_robotlaser(path: Path, tokens: list[str], lineno: int, out: _Lines) -> None:
    kind = tokens[0]
    if len(tokens) < 9:
        raise _too_short(path, kind, lineno, 9, len(tokens))
    n = _beam_count(path, tokens, 8, lineno, kind)
    if len(tokens) < 10 + n:
        raise _too_short(path, kind, lineno, 10 + n, len(tokens))
    try:
        n_rem = int(tokens[9 + n])
    except ValueError:
        raise FormatError(
            path,
            f"{kind}: remission count must be an integer, got {tokens[9 + n]!r}",
            location=f"line {lineno}",
        ) from None
    start = 10 + n + n_rem
    need = start + 12  # laser pose, robot pose, 5 velocities/safety values, timestamp
    if len(tokens) < need:
        raise _too_short(path, kind, lineno, need + 2, len(tokens))
    head = _numbers(path, tokens[2:6], lineno, kind)
    ranges = _numbers(path, tokens[9 : 9 + n], lineno, kind)
    tail = _numbers(path, tokens[start:need], lineno, kind)
    out.line_numbers.append(lineno)
    out.ranges.append(ranges)
    # tail: robot pose (3), laser pose (3), stamp -- same slots as FLASER's (pose, odom, stamp)
    out.tails.append(np.concatenate([tail[3:6], tail[0:3], tail[11:12]]))
    out.geometry.append((float(head[0]), float(head[2]), float(head[3])))


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
        corrected: Treat the log as SLAM-corrected (None: decide from the file name).
    """

    max_range: float | None = None
    corrected: bool | None = None
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
            FormatError: Truncated gzip, garbled or truncated line, zero-beam scan (the
                message names the file and line number).
        """
        path = Path(path)
        text = read_carmen_text(path)
        lasers: dict[str, _Lines] = {k: _Lines([], [], [], []) for k in LASER_MESSAGES}
        counts: dict[str, int] = {}
        odom_rows: list[list[str]] = []
        odom_lines: list[int] = []
        params: dict[str, str] = {}
        old_style: dict[str, list[tuple[int, str]]] = {"FLASER": [], "RLASER": []}
        for lineno, line in enumerate(text.split("\n"), start=1):
            if not line or line[0] == "#":
                continue
            if line.startswith(("FLASER ", "RLASER ")):
                kind = line[:6]
                counts[kind] = counts.get(kind, 0) + 1
                old_style[kind].append((lineno, line))
                continue
            tokens = line.split()
            if not tokens:
                continue
            kind = tokens[0]
            counts[kind] = counts.get(kind, 0) + 1
            if kind in ("FLASER", "RLASER"):
                old_style[kind].append((lineno, line))
            elif kind == "ROBOTLASER1":
                _parse_robotlaser(path, tokens, lineno, lasers[kind])
            elif kind == "ODOM":
                if len(tokens) < 8:
                    raise _too_short(path, kind, lineno, 10, len(tokens))
                odom_rows.append(tokens[1:4] + tokens[7:8])
                odom_lines.append(lineno)
            elif kind == "PARAM" and len(tokens) >= 3:
                params[tokens[1]] = tokens[2]

        for kind, raw_lines in old_style.items():
            if raw_lines:
                _parse_flaser_lines(path, raw_lines, lasers[kind])
        present = [k for k in LASER_MESSAGES if lasers[k].ranges]
        if not present:
            found = ", ".join(f"{k} ({v})" for k, v in sorted(counts.items())) or "nothing"
            raise InputError(
                path, f"no laser lines (FLASER, RLASER or ROBOTLASER1) in the log; found {found}"
            )
        if scan_topic is None:
            kind = present[0]
            if len(present) > 1:
                log.info("%s: laser types %s present; using %s", path, present, kind)
        else:
            kind = scan_topic.upper()
            if kind not in present:
                raise InputError(
                    path,
                    f"no {scan_topic} lines; laser types present: {', '.join(present)}",
                    location=f"topic {scan_topic}",
                )
        data = lasers[kind]

        # ipc_timestamp: when the laser message was sent (the logger stamp adds queueing).
        tails = np.stack(data.tails)
        pose, embedded_odom, stamps = tails[:, 0:3], tails[:, 3:6], tails[:, 6].copy()
        pose[:, 2] = wrap_angle(pose[:, 2])
        embedded_odom[:, 2] = wrap_angle(embedded_odom[:, 2])

        if kind == "ROBOTLASER1":
            max_range = self.max_range
            sensor_name = "CARMEN ROBOTLASER1"
        else:
            max_range = self.max_range if self.max_range is not None else _clip_code(data.ranges)
            sensor_name = f"SICK LMS (CARMEN {kind})"
        scans: list[LaserScan] = []
        for lineno, r, (amin, inc, mr) in zip(
            data.line_numbers, data.ranges, data.geometry, strict=True
        ):
            limit = max_range if max_range is not None else mr
            r = np.where(r >= limit, np.inf, r)
            try:
                scans.append(
                    LaserScan(
                        stamp=float(stamps[len(scans)]),
                        ranges=r.astype(np.float32),
                        angle_min=amin,
                        angle_increment=inc,
                        range_min=CARMEN_RANGE_MIN,
                        range_max=float(limit),
                    )
                )
            except ScanError as exc:
                raise FormatError(path, f"{kind}: {exc}", location=f"line {lineno}") from None

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
        metadata: dict[str, Any] = {
            "format": self.name,
            "source": str(path),
            "path": str(path),
            "scan_topic": kind,
            "topics": {k: {"type": f"carmen/{k}", "count": v} for k, v in sorted(counts.items())},
        }
        for key in ("robot_frontlaser_offset", "robot_rearlaser_offset"):
            if key in params:
                metadata[f"carmen_{key}"] = params[key]

        if diffs.size and np.unique(stamps).size < 0.5 * stamps.size:
            note = (
                f"only {np.unique(stamps).size} distinct stamps for {stamps.size} scans "
                "(the log stores rounded times)"
            )
            metadata["stamps_unreliable"] = note
            log.warning("%s: %s; rate and duration are unknown", path, note)
        elif diffs.size and np.any(diffs <= 0):
            bad = int((diffs <= 0).sum())
            metadata["stamps_not_increasing"] = bad
            log.warning(
                "%s: %d of %d consecutive laser stamps do not increase (largest step back "
                "%.3f s); kept in file order",
                path,
                bad,
                diffs.size,
                float(-diffs.min()),
            )

        corrected = self.corrected
        if corrected is None:
            corrected = "corrected" in path.name.lower()
        metadata["carmen_corrected"] = corrected

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
                    f"unknown reference source {ref_choice!r} for a CARMEN log (use 'laser')",
                    location=f"topic {ref_choice}",
                )
            reference = pose.copy()
            reference_kind = "corrected_log" if corrected else "log_pose"
            metadata["reference_source"] = f"{kind} pose"

        odometry: NDArray[np.float64] | None = None
        odom_choice = odom_topic
        if odom_choice is None:
            odom_choice = None if corrected else "laser"
        if odom_choice is not None:
            if odom_choice.upper() == "ODOM":
                if not odom_rows:
                    raise InputError(path, "no ODOM lines in the log", location="topic ODOM")
                if "stamps_unreliable" in metadata:
                    raise InputError(
                        path,
                        "cannot align ODOM lines with laser lines: the log's stamps are rounded",
                        location="topic ODOM",
                    )
                od = np.empty((len(odom_rows), 4))
                for i, (row, ln) in enumerate(zip(odom_rows, odom_lines, strict=True)):
                    od[i] = _numbers(path, row, ln, "ODOM")
                if corrected:
                    log.warning(
                        "%s: ODOM lines of a corrected log are not aligned with its scans", path
                    )
                odometry = align_poses(path, "ODOM lines", od[:, 3], od[:, :3], stamps)
                metadata["odometry_source"] = "ODOM lines"
            elif odom_choice.lower() in ("laser", kind.lower()):
                odometry = embedded_odom
                metadata["odometry_source"] = f"{kind} odometry fields"
            else:
                raise InputError(
                    path,
                    f"unknown odometry source {odom_choice!r} for a CARMEN log "
                    "(use 'ODOM' or 'laser')",
                    location=f"topic {odom_choice}",
                )

        name = path.name
        for suffix in sorted(self.extensions, key=len, reverse=True):
            if name.lower().endswith(suffix):
                name = name[: -len(suffix)]
                break
        log.debug("%s: %d %s scans", path, len(scans), kind)
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
