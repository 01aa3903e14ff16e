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

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, ScanError
from scanguard.geometry import relative, wrap_angle
from scanguard.io._carmen_lines import _clip_code, _Lines, _odom_table, _Problems
from scanguard.io._carmen_scan import (
    CARMEN_MESSAGES,
    CARMEN_RANGE_MIN,
    LASER_MESSAGES,
    TOPIC_MESSAGES,
    _Limit,
    _Log,
    _scan_log,
)
from scanguard.io.base import (
    MAX_NAMES,
    align_poses,
    describe_counts,
    printable,
    read_file_bytes,
    warn_once,
)
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

log = logging.getLogger(__name__)

__all__ = ["LASER_MESSAGES", "TOPIC_MESSAGES", "CarmenReader", "read_carmen_text"]

_SNIFF = 4096  # bytes looked at to tell text from binary

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
    # a byte-order mark (Windows editors) would glue itself to the first line's type
    data = data.removeprefix(b"\xef\xbb\xbf")
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        # Host names in old logs are occasionally latin-1; numbers are ASCII either way.
        text = data.decode("latin-1")
    if "\r" in text:  # CRLF and CR-only (old Mac) line endings: one line per line
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    return text


def _refuse_binary(path: Path, data: bytes) -> None:
    """Raise "not a CARMEN log" for a known binary format or NUL bytes at the start."""
    for magic, what in _BINARY_MAGIC:
        if data.startswith(magic):
            raise FormatError(path, f"not a CARMEN log (it is {what}; CARMEN logs are text)")
    if b"\x00" in data[:_SNIFF]:
        raise FormatError(path, "not a CARMEN log (binary data; CARMEN logs are text)")


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def _sensor(name: str, s0: LaserScan, diffs: NDArray[np.float64]) -> SensorInfo:
    """The sensor: geometry of the first scan, rate from the median positive stamp step."""
    pos = diffs[diffs > 0]
    rate = float(1.0 / np.median(pos)) if pos.size > diffs.size // 2 else None
    return SensorInfo(
        name=name,
        n_beams=s0.n_beams,
        angle_min=s0.angle_min,
        angle_increment=s0.angle_increment,
        range_min=s0.range_min,
        range_max=s0.range_max,
        rate_hz=rate,
    )


def _check_stamps(
    path: Path, stamps: NDArray[np.float64], diffs: NDArray[np.float64], metadata: dict[str, Any]
) -> None:
    """Note (in ``metadata``, and warn once) rounded or non-increasing laser stamps."""
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


def _laser_offset(
    kind: str, pose: NDArray[np.float64], embedded_odom: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The laser offset of a message type, and the odometry its lines embed."""
    laser_offset = np.zeros(3)
    if kind == "RLASER":
        laser_offset = np.array([0.0, 0.0, np.pi])
    elif kind == "ROBOTLASER1":
        laser_offset = relative(pose[0], embedded_odom[0])
        # robot pose and laser pose share the slots of FLASER's (pose, odom): the
        # second one is the laser, not odometry, for this message type.
        embedded_odom = pose.copy()
    return laser_offset, embedded_odom


def _reference(
    path: Path,
    kind: str,
    pose: NDArray[np.float64],
    choice: str | None,
    corrected: bool,
    metadata: dict[str, Any],
) -> tuple[NDArray[np.float64] | None, str | None]:
    """The reference poses and kind: the laser lines' poses where chosen (or corrected)."""
    if choice is None:
        choice = "laser" if corrected else None
    if choice is None:
        metadata["reference_hint"] = (
            "if the poses of this CARMEN log are SLAM-corrected, read it as a corrected "
            "log (corrected=True, CLI --corrected): its poses become the reference"
        )
        return None, None
    if choice.lower() not in ("laser", kind.lower()):
        raise InputError(
            path,
            f"unknown reference source {printable(choice)!r} for a CARMEN log (use 'laser')",
            location=f"topic {printable(choice)}",
        )
    metadata["reference_source"] = f"{kind} pose"
    return pose.copy(), "corrected_log" if corrected else "log_pose"


def _odometry_hint(n_rows: int, metadata: dict[str, Any]) -> None:
    """Say in ``metadata`` why the log's ODOM lines are not used."""
    if "stamps_unreliable" in metadata:
        metadata["odometry_hint"] = (
            f"the log has {n_rows} ODOM lines, but its rounded stamps cannot "
            "align them with the scans"
        )
    else:
        metadata["odometry_hint"] = (
            f"not used by default: the log has {n_rows} ODOM lines (raw "
            "odometry, not aligned with the corrected poses); --odom-topic ODOM "
            "uses them"
        )


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
        max_scans: Stop reading after this many laser lines of the type read (None: all);
            ODOM lines are read on until one passes the last of them, so the scans and their
            odometry are those of a full read (with lines skipped by a lenient read, fewer).
    """

    max_range: float | None = None
    corrected: bool | None = None
    lenient: bool = False
    max_scans: int | None = None
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
        problems = _Problems(path, self.lenient)
        limit = None if self.max_scans is None else _Limit(self.max_scans, scan_topic)
        found = _scan_log(path, read_carmen_text(path), problems, limit)
        kind = self._choose_kind(path, found, problems, scan_topic)
        scans, data = self._scans(path, kind, found, problems)

        # ipc_timestamp: when the laser message was sent (the logger stamp adds queueing).
        tails = np.stack(data.tails)
        pose, embedded_odom, stamps = tails[:, 0:3], tails[:, 3:6], tails[:, 6].copy()
        pose[:, 2] = wrap_angle(pose[:, 2])
        embedded_odom[:, 2] = wrap_angle(embedded_odom[:, 2])
        diffs = np.diff(stamps)
        sensor_name = "CARMEN ROBOTLASER1" if kind == "ROBOTLASER1" else f"SICK LMS (CARMEN {kind})"
        sensor = _sensor(sensor_name, scans[0], diffs)
        metadata = self._metadata(path, kind, found)
        _check_stamps(path, stamps, diffs, metadata)
        corrected = self._is_corrected(path, found, metadata)

        laser_offset, embedded_odom = _laser_offset(kind, pose, embedded_odom)
        reference, reference_kind = _reference(
            path, kind, pose, reference_topic, corrected, metadata
        )
        odom_choice = odom_topic
        if odom_choice is None:
            odom_choice = None if corrected else "laser"
        odometry: NDArray[np.float64] | None = None
        if odom_choice is not None:
            odometry = self._odometry(
                path, kind, odom_choice, found, embedded_odom, stamps, metadata, corrected, problems
            )
        elif found.odom_rows:
            _odometry_hint(len(found.odom_rows), metadata)

        if limit is not None and limit.stopped:
            metadata["max_scans"] = self.max_scans
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

    def _choose_kind(
        self, path: Path, found: _Log, problems: _Problems, scan_topic: str | None
    ) -> str:
        """The laser message type to read: the chosen one, else the first present."""
        present = [k for k in LASER_MESSAGES if found.lasers[k].ranges]
        if not present:
            self._no_laser(path, found.counts, found.others, problems)
        if scan_topic is None:
            kind = present[0]
            if len(present) > 1:
                log.info("%s: laser types %s present; using %s", path, present, kind)
            return kind
        kind = scan_topic.upper()
        if kind not in present:
            raise InputError(
                path,
                f"no {printable(scan_topic)} lines; laser types present: {', '.join(present)}",
                location=f"topic {printable(scan_topic)}",
            )
        return kind

    def _scans(
        self, path: Path, kind: str, found: _Log, problems: _Problems
    ) -> tuple[list[LaserScan], _Lines]:
        """The scans of the ``kind`` lines, and those lines (less the invalid scans)."""
        data = found.lasers[kind]
        if kind == "ROBOTLASER1":
            max_range = self.max_range
        else:
            max_range = self.max_range if self.max_range is not None else _clip_code(data.ranges)
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
            self._no_laser(path, found.counts, found.others, problems)
        if self.max_scans is not None:  # other laser types may have run past it
            kept = kept[: self.max_scans]
            scans = scans[: self.max_scans]
        if len(kept) < len(data.tails):
            data = data.keep(np.isin(np.arange(len(data.tails)), kept))
        return scans, data

    def _metadata(self, path: Path, kind: str, found: _Log) -> dict[str, Any]:
        """The metadata every read has: format, source, topics, other lines, laser offsets."""
        ranked = sorted(found.others.items(), key=lambda kv: (-kv[1], kv[0]))
        other_lines = {printable(k): v for k, v in ranked[:MAX_NAMES]}
        if len(ranked) > MAX_NAMES:
            rest = ranked[MAX_NAMES:]
            other_lines[f"({len(rest)} more kinds)"] = sum(v for _, v in rest)
        counts = found.counts
        metadata: dict[str, Any] = {
            "format": self.name,
            "source": str(path),
            "path": str(path),
            "scan_topic": kind,
            "topics": {k: {"type": f"carmen/{k}", "count": v} for k, v in sorted(counts.items())},
            "other_lines": other_lines,
        }
        for key in ("robot_frontlaser_offset", "robot_rearlaser_offset"):
            if key in found.params:
                metadata[f"carmen_{key}"] = printable(found.params[key])
        return metadata

    def _is_corrected(self, path: Path, found: _Log, metadata: dict[str, Any]) -> bool:
        """Whether the log is SLAM-corrected: the option, else its name, else NEFF lines."""
        corrected = self.corrected
        by = "option"
        if corrected is None:
            if "corrected" in path.name.lower():
                corrected, by = True, "file name"
            elif found.others.get("NEFF", 0) > 0:
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
        return corrected

    def _odometry(
        self,
        path: Path,
        kind: str,
        choice: str,
        found: _Log,
        embedded_odom: NDArray[np.float64],
        stamps: NDArray[np.float64],
        metadata: dict[str, Any],
        corrected: bool,
        problems: _Problems,
    ) -> NDArray[np.float64]:
        """The chosen odometry: ODOM lines, or the odometry fields of the laser lines."""
        if choice.upper() == "ODOM":
            odometry = self._odom_lines(
                path, found.odom_rows, found.odom_lines, stamps, metadata, corrected, problems
            )
            metadata["odometry_source"] = "ODOM lines"
            return odometry
        if choice.lower() in ("laser", kind.lower()):
            metadata["odometry_source"] = f"{kind} odometry fields"
            return embedded_odom
        raise InputError(
            path,
            f"unknown odometry source {printable(choice)!r} for a CARMEN log "
            "(use 'ODOM' or 'laser')",
            location=f"topic {printable(choice)}",
        )

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
        od = _odom_table(path, rows, line_numbers, problems)
        if od.size == 0:
            raise FormatError(path, "no usable ODOM lines", location="topic ODOM")
        if corrected:
            warn_once(log, path, "ODOM lines of a corrected log are not aligned with its scans")
        return align_poses(path, "ODOM lines", od[:, 3], od[:, :3], stamps)
