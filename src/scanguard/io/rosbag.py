"""Read ROS bags through `rosbags`: ROS 1 ``.bag``, ROS 2 bag folders, ``.db3`` and ``.mcap``.

Reading (`RosbagReader`) uses ``rosbags.highlevel.AnyReader``:

* scans come from one ``sensor_msgs/LaserScan`` topic, stamped with their header stamps;
* odometry (``nav_msgs/Odometry``) and the optional reference (``nav_msgs/Odometry``,
  ``geometry_msgs/PoseStamped`` or ``PoseWithCovarianceStamped``) are interpolated to the
  scan stamps;
* the laser offset comes from ``/tf_static`` (a transform whose child is the scan frame).

Accepted paths: a ROS 1 ``.bag``; a ROS 2 bag folder (with ``metadata.yaml``); the
``.mcap``/``.db3`` file inside such a folder (the folder is opened); a standalone ``.mcap``.

A bag written by `scanguard.io.rosbag_writer.write_rosbag` carries one ``std_msgs/String``
on ``/scanguard/info`` (JSON: sequence name, sensor name, reference kind, topics, metadata);
the reader uses it to restore the sequence exactly.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, ScanError
from scanguard.io.base import (
    LENIENT_HINT,
    MAX_NAMES,
    QUATERNION_TOLERANCE,
    align_poses,
    bad_pose_rows,
    beams_disagree,
    check_recording_path,
    planar_yaw,
    pose_problem,
    printable,
    stamps_note,
    warn_once,
)
from scanguard.io.rosbag_info import INFO_TOPIC, laser_offset_of, parse_info
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

log = logging.getLogger(__name__)

__all__ = ["INFO_TOPIC", "RosbagReader"]

LASERSCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_TYPES = (
    ODOMETRY,
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)
GROUND_TRUTH_NAMES = ("ground_truth", "base_pose_ground_truth", "groundtruth")


def _norm(topic: str) -> str:
    # ROS 1 bags may store topics without the leading slash ("right_scan").
    return topic.strip().lstrip("/")


def laser_scan_of(msg: Any, stamp: float) -> LaserScan:
    """A `LaserScan` of a ``sensor_msgs/LaserScan`` message (ROS 1, ROS 2 or rosbags).

    Bag readers and the live node build scans here, so a message is checked the same way
    wherever it comes from.

    Raises:
        ScanError: The ranges array disagrees with the angle fields (which of the two is right
            is unknown), or the scan's own checks fail.
    """
    disagree = beams_disagree(len(msg.ranges), msg.angle_min, msg.angle_max, msg.angle_increment)
    if disagree is not None:
        raise ScanError(disagree)
    return LaserScan(
        stamp=stamp,
        ranges=np.asarray(msg.ranges, dtype=np.float32),
        angle_min=float(msg.angle_min),
        angle_increment=float(msg.angle_increment),
        range_min=float(msg.range_min),
        range_max=float(msg.range_max),
        intensities=np.asarray(msg.intensities, dtype=np.float32),
    )


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def _pose_of(msg: Any) -> tuple[float, float, NDArray[np.float64]]:
    """Position x, y and the orientation quaternion (x, y, z, w) of a pose message."""
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    q = pose.orientation
    return float(pose.position.x), float(pose.position.y), np.array([q.x, q.y, q.z, q.w])


MCAP_MAGIC = b"\x89MCAP0\r\n"


def _check_mcap(path: Path) -> None:
    """Refuse an MCAP file that lacks its start or end magic (truncated, or not MCAP at all)."""
    if not path.is_file():  # never open a FIFO or device: it could block
        return
    try:
        size = path.stat().st_size
        with path.open("rb") as fh:
            head = fh.read(len(MCAP_MAGIC))
            fh.seek(max(0, size - len(MCAP_MAGIC)))
            tail = fh.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    if head != MCAP_MAGIC:
        raise FormatError(path, "not an MCAP file (no MCAP magic at the start)")
    if size < 2 * len(MCAP_MAGIC) or tail != MCAP_MAGIC:
        raise FormatError(path, f"truncated MCAP file ({size} bytes, no end magic)")


def _resolve_bag_path(path: Path) -> Path:
    if not path.exists():
        raise InputError(path, "file not found")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path
        storages = sorted([*path.glob("*.mcap"), *path.glob("*.db3")])
        if len(storages) != 1:
            raise InputError(
                path, "folder is not a ROS 2 bag (no metadata.yaml and not exactly one .mcap/.db3)"
            )
        path = storages[0]
    elif path.suffix in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file():
        path = path.parent
    for mcap in sorted(path.glob("*.mcap")) if path.is_dir() else [path]:
        if mcap.suffix == ".mcap":
            _check_mcap(mcap)
    return path


@dataclass
class RosbagReader:
    """Reader for ROS 1 and ROS 2 bags (see the module docstring).

    Malformed messages (a scan with zero beams, a non-finite angle or a field of view outside
    (0, 360] degrees; a pose that is not finite or beyond 1e6 m) are errors naming the bag,
    the topic and the message.

    Attributes:
        lenient: Skip malformed messages instead (one warning gives their count).
        max_scans: Stop reading after this many scans (None: all). The pose topics are read
            on until they pass the last of those scans, so the scans and their odometry and
            reference are those of a full read.
    """

    lenient: bool = False
    max_scans: int | None = None
    name: str = "rosbag"
    extensions: tuple[str, ...] = (".bag", ".mcap", ".db3", "")

    def read(
        self,
        path: Path,
        *,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        reference_topic: str | None = None,
    ) -> ScanSequence:
        """Read a bag into a `ScanSequence`.

        Args:
            path: Bag file or folder.
            scan_topic: LaserScan topic; needed only when the bag has several.
            odom_topic: Odometry topic; default: the only ``nav_msgs/Odometry`` topic that is
                not the reference topic (none when there are several).
            reference_topic: Reference pose topic; default: the one recorded by our writer,
                else a topic named ``ground_truth``/``base_pose_ground_truth``, else none.

        Raises:
            InputError: Missing file, unknown or ambiguous topic, no LaserScan topic (the
                message names the topics found).
            FormatError: The bag cannot be parsed, or a scan is malformed (zero beams).
        """
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.rosbag1 import ReaderError as Reader1Error
        from rosbags.rosbag2 import ReaderError as Reader2Error
        from rosbags.typesys import Stores, get_typestore

        path = check_recording_path(path)
        bag = _resolve_bag_path(path)
        errors = (
            AnyReaderError,
            Reader1Error,
            Reader2Error,
            KeyError,
            ValueError,
            EOFError,
            IndexError,
            struct.error,
        )
        try:
            with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
                return self._read_open(path, reader, scan_topic, odom_topic, reference_topic)
        except errors as exc:
            raise FormatError(
                path, f"cannot read bag ({type(exc).__name__}: {printable(str(exc), 160)})"
            ) from None
        except RecursionError:  # e.g. a metadata.yaml nested 50k deep
            raise FormatError(path, "cannot read bag (metadata nested too deeply)") from None
        except FileNotFoundError as exc:
            raise InputError(path, f"cannot open bag ({exc})") from None
        except ScanError as exc:  # e.g. a non-finite laser offset in /tf_static
            raise FormatError(path, str(exc)) from None

    def _read_open(
        self,
        path: Path,
        reader: Any,
        scan_topic: str | None,
        odom_topic: str | None,
        reference_topic: str | None,
    ) -> ScanSequence:
        index = _TopicIndex.of(path, reader)
        info = _read_info(path, reader, index, self.lenient)
        scan = _choose_scan(index, info, scan_topic)
        ref, odom = _choose_pose_topics(index, info, odom_topic, reference_topic)
        poses: dict[str, tuple[list[float], list[tuple[float, float, float]]]] = {
            t: ([], []) for t in (odom, ref) if t is not None
        }
        msgs = _Messages(path, self.lenient, scan, poses, max_scans=self.max_scans)
        msgs.read(reader, index)
        scans = msgs.scans
        stamps, back = _stamps_in_order(path, scans, scan)
        unreliable = stamps_note(stamps, f"header stamp(s) on {printable(scan)}")
        if unreliable is not None:
            warn_once(log, path, f"{unreliable}; rate and duration are unknown")
            odom = _unaligned(path, odom, odom_topic, unreliable)
            ref = _unaligned(path, ref, reference_topic, unreliable)
        odometry = msgs.aligned(odom, stamps)
        reference = msgs.aligned(ref, stamps)
        laser_offset = laser_offset_of(path, info, msgs.statics, msgs.frame_id, self.lenient)
        metadata: dict[str, Any] = dict(info.get("metadata") or {})
        # a sequence we wrote keeps its own "source" (e.g. "scanguard.sim"); "path" is the file
        metadata.setdefault("source", str(path))
        metadata.update(
            {
                "format": self.name,
                "path": str(path),
                "scan_topic": scan,
                "frame_id": msgs.frame_id,
                "topics": index.topics,
            }
        )
        if back.any():
            metadata["stamps_not_increasing"] = int(back.sum())
        if unreliable is not None:
            metadata["stamps_unreliable"] = unreliable
        if msgs.skipped:
            metadata["skipped_lines"] = len(msgs.skipped)
        if msgs.stopped:
            metadata["max_scans"] = self.max_scans
        if odom is not None:
            metadata["odometry_source"] = odom
        if ref is not None:
            metadata["reference_source"] = ref
        reference_kind = None
        if reference is not None:
            reference_kind = str(info.get("reference_kind") or "ground_truth")
        name = info.get("name") or (path.stem if path.suffix else path.name)
        return ScanSequence(
            name=str(name),
            scans=scans,
            sensor=_sensor(info, scans[0], msgs.frame_id, msgs.scan_time),
            odometry=odometry,
            reference=reference,
            reference_kind=reference_kind,
            laser_offset=laser_offset,
            metadata=metadata,
        )


def _unaligned(path: Path, topic: str | None, chosen: str | None, note: str) -> str | None:
    """None for a pose topic that cannot be aligned with unreliable scan stamps.

    A topic the user chose is refused (`InputError`); one picked by default is dropped with a
    warning, so the scans can still be read.
    """
    if topic is None:
        return None
    problem = f"cannot align {printable(topic)} with the scans: {note}"
    if chosen is not None:
        raise InputError(path, problem, location=f"topic {printable(topic)}")
    warn_once(log, path, f"{problem}; not used")
    return None


@dataclass
class _TopicIndex:
    """The topics of an open bag: type and message count, connections, normalised names."""

    path: Path
    topics: dict[str, dict[str, Any]]
    conns_by_topic: dict[str, list[Any]]
    by_norm: dict[str, str]

    @classmethod
    def of(cls, path: Path, reader: Any) -> _TopicIndex:
        topics: dict[str, dict[str, Any]] = {}
        conns_by_topic: dict[str, list[Any]] = {}
        for c in reader.connections:
            entry = topics.setdefault(c.topic, {"type": c.msgtype, "count": 0})
            entry["count"] += int(c.msgcount)
            if c.msgtype != entry["type"]:
                # one topic recorded with two message types: never deserialise one as the other
                entry.setdefault("other_types", []).append(c.msgtype)
            conns_by_topic.setdefault(c.topic, []).append(c)
        return cls(path, topics, conns_by_topic, {_norm(t): t for t in topics})

    def found(self) -> str:
        """The topics found (for error messages)."""
        names = [
            f"{printable(t)} ({printable(v['type'], 48)})" for t, v in sorted(self.topics.items())
        ]
        if len(names) > MAX_NAMES:
            names = [*names[:MAX_NAMES], f"and {len(names) - MAX_NAMES} more"]
        return ", ".join(names) or "none"

    def lookup(self, topic: str, allowed: tuple[str, ...], role: str) -> str:
        """The bag's name of a topic the user chose; `InputError` if missing or mistyped."""
        path, topics = self.path, self.topics
        real = self.by_norm.get(_norm(topic))
        if real is None:
            raise InputError(
                path,
                f"no {role} topic {printable(topic)!r}; topics found: {self.found()}",
                location=f"topic {printable(topic)}",
            )
        _refuse_mixed(path, real, topics[real])
        if topics[real]["type"] not in allowed:
            raise InputError(
                path,
                f"{role} topic has type {printable(topics[real]['type'], 48)}, expected "
                f"{' or '.join(allowed)}",
                location=f"topic {printable(real)}",
            )
        return real


def _refuse_mixed(path: Path, topic: str, entry: dict[str, Any]) -> None:
    """`FormatError` for a topic used by the reader whose connections differ in type."""
    others = entry.get("other_types")
    if others:
        types = ", ".join(printable(t, 48) for t in sorted({entry["type"], *others}))
        raise FormatError(
            path,
            f"topic recorded with several message types ({types})",
            location=f"topic {printable(topic)}",
        )


def _read_info(path: Path, reader: Any, index: _TopicIndex, lenient: bool) -> dict[str, Any]:
    """Our writer's info message, checked (empty if the bag has none).

    A malformed one is a `FormatError`; a lenient read ignores it with a warning and reads
    the bag as any other.
    """
    string = "std_msgs/msg/String"
    conns = [c for c in index.conns_by_topic.get(INFO_TOPIC, []) if c.msgtype == string]
    # an empty list would mean every connection to rosbags
    for c, _, raw in reader.messages(connections=conns) if conns else ():
        try:
            return parse_info(path, str(reader.deserialize(raw, c.msgtype).data))
        except FormatError as exc:
            if not lenient:
                hint = " (a lenient read, --lenient, ignores it)"
                raise FormatError(path, exc.problem + hint, location=exc.location) from None
            warn_once(log, path, f"topic {INFO_TOPIC}: ignored: {exc.problem}")
        break
    return {}


def _choose_scan(index: _TopicIndex, info: dict[str, Any], scan_topic: str | None) -> str:
    """The LaserScan topic: the chosen one, the only one, or the one our writer recorded."""
    path, topics = index.path, index.topics
    laser_topics = sorted(t for t, v in topics.items() if v["type"] == LASERSCAN)
    if scan_topic is not None:
        return index.lookup(scan_topic, (LASERSCAN,), "LaserScan")
    if not laser_topics:
        raise InputError(path, f"no sensor_msgs/LaserScan topic; topics found: {index.found()}")
    if len(laser_topics) == 1:
        return laser_topics[0]
    if info.get("scan_topic") in laser_topics:
        return str(info["scan_topic"])
    raise InputError(
        path,
        f"several LaserScan topics ({', '.join(map(printable, laser_topics))}); "
        "choose one with --scan-topic",
    )


def _choose_pose_topics(
    index: _TopicIndex,
    info: dict[str, Any],
    odom_topic: str | None,
    reference_topic: str | None,
) -> tuple[str | None, str | None]:
    """The reference and odometry topics (each None when there is none to use)."""
    path, topics = index.path, index.topics
    pose_topics = sorted(t for t, v in topics.items() if v["type"] in POSE_TYPES)
    ref: str | None = None
    if reference_topic is not None:
        ref = index.lookup(reference_topic, POSE_TYPES, "reference")
    elif info.get("reference_topic") in pose_topics:
        ref = info["reference_topic"]
    else:
        named = [t for t in pose_topics if _norm(t) in GROUND_TRUTH_NAMES]
        ref = named[0] if len(named) == 1 else None
    odom: str | None = None
    if odom_topic is not None:
        odom = index.lookup(odom_topic, POSE_TYPES, "odometry")
    elif info.get("odom_topic") in pose_topics and info.get("odom_topic") != ref:
        odom = info["odom_topic"]
    else:
        candidates = [t for t in pose_topics if topics[t]["type"] == ODOMETRY and t != ref]
        if len(candidates) == 1:
            odom = candidates[0]
        elif candidates:
            log.warning(
                "%s: several Odometry topics (%s); none used as odometry, choose one with "
                "--odom-topic",
                path,
                ", ".join(map(printable, candidates)),
            )
    return ref, odom


@dataclass
class _Messages:
    """The scans, poses and static transforms read from a bag, in bag order."""

    path: Path
    lenient: bool
    scan: str
    poses: dict[str, tuple[list[float], list[tuple[float, float, float]]]]
    scans: list[LaserScan] = field(default_factory=list)
    frame_id: str = ""
    scan_time: float = 0.0
    statics: list[Any] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    n_scan_msgs: int = 0
    repaired: dict[str, int] = field(default_factory=dict)
    max_scans: int | None = None
    stopped: bool = False  # reading stopped at max_scans (the rest of the bag is unread)
    _last: float | None = None  # latest stamp of the scans kept (once max_scans is reached)

    def malformed(self, topic: str, what: str) -> None:
        """Raise `FormatError` for a malformed message, or (lenient) note it as skipped."""
        if not self.lenient:
            raise FormatError(self.path, what + LENIENT_HINT, location=f"topic {printable(topic)}")
        self.skipped.append(f"topic {printable(topic)}: {what}")

    def read(self, reader: Any, index: _TopicIndex) -> None:
        """Read the scan and pose topics and ``/tf_static``; `InputError` if no scan is usable."""
        path, scan = self.path, self.scan
        wanted = [scan, *self.poses]
        for t in wanted:
            _refuse_mixed(path, t, index.topics[t])
        conns = [c for t in wanted for c in index.conns_by_topic[t]]
        tf = "tf2_msgs/msg/TFMessage"
        conns += [c for c in index.conns_by_topic.get("/tf_static", []) if c.msgtype == tf]
        wants_statics = any(c.msgtype == tf for c in conns)
        for c, bag_ns, raw in reader.messages(connections=conns):
            if self.max_scans is not None and len(self.scans) >= self.max_scans:
                if self._enough(wants_statics):
                    self.stopped = True
                    break
                if c.topic == scan:  # past the limit: only poses and transforms still count
                    continue
            try:
                msg = reader.deserialize(raw, c.msgtype)
            except Exception as exc:
                self.malformed(c.topic, f"cannot decode a message ({type(exc).__name__})")
                continue
            if c.topic == scan:
                self._add_scan(msg, bag_ns)
            elif c.topic in self.poses:
                self._add_pose(c.topic, msg, bag_ns)
            elif c.msgtype == "tf2_msgs/msg/TFMessage":
                self.statics.extend(msg.transforms)
        for topic, n in self.repaired.items():
            warn_once(log, path, f"topic {printable(topic)}: {n} {_REPAIRED[topic == scan]}")
        skipped = self.skipped
        if skipped:
            warn_once(
                log,
                path,
                f"lenient read: skipped {len(skipped)} malformed message(s) (first: {skipped[0]})",
            )
        if not self.scans:
            what = "has no usable messages" if skipped else "has no messages"
            raise InputError(path, f"LaserScan topic {what}", location=f"topic {printable(scan)}")

    def _enough(self, wants_statics: bool) -> bool:
        """Whether reading may stop: every pose topic has passed the last scan kept.

        A pose stream is interpolated between its two samples around each scan stamp, so once
        a pose is stamped at or after the latest kept scan, later poses change nothing.
        """
        if wants_statics and not self.statics:
            return False
        if self._last is None:
            self._last = max(s.stamp for s in self.scans)
        return all(t and t[-1] >= self._last for t, _ in self.poses.values())

    def _add_scan(self, msg: Any, bag_ns: int) -> None:
        stamp = _stamp(msg.header)
        if stamp == 0.0:
            stamp = bag_ns * 1e-9  # some drivers leave header stamps empty
        if float(msg.range_min) < 0:  # LaserScan clamps it to 0; say so
            self.repaired[self.scan] = self.repaired.get(self.scan, 0) + 1
        try:
            self.scans.append(laser_scan_of(msg, stamp))
        except ScanError as exc:
            self.malformed(self.scan, f"message {self.n_scan_msgs}: {exc}")
        self.n_scan_msgs += 1
        if not self.frame_id:
            self.frame_id = msg.header.frame_id
            self.scan_time = float(msg.scan_time)

    def _add_pose(self, topic: str, msg: Any, bag_ns: int) -> None:
        stamp = _stamp(msg.header)
        x, y, q = _pose_of(msg)
        yaw, repaired, unusable = planar_yaw(q)
        pose = (x, y, float(yaw[0]))
        k = len(self.poses[topic][0])
        if bad_pose_rows(np.array(pose))[0]:
            self.malformed(topic, f"message {k}: {pose_problem(np.array(pose))}")
            return
        if unusable[0]:
            self.malformed(topic, f"message {k}: zero or non-finite orientation quaternion")
            return
        if repaired[0]:
            self.repaired[topic] = self.repaired.get(topic, 0) + 1
        self.poses[topic][0].append(stamp if stamp != 0.0 else bag_ns * 1e-9)
        self.poses[topic][1].append(pose)

    def aligned(self, topic: str | None, stamps: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """A pose topic interpolated to the scan stamps (None for no topic)."""
        if topic is None:
            return None
        t, p = self.poses[topic]
        return align_poses(
            self.path, f"topic {topic}", np.array(t), np.array(p, dtype=np.float64), stamps
        )


_REPAIRED = {
    False: f"orientation quaternion(s) off unit norm by more than {QUATERNION_TOLERANCE}; "
    "normalised",
    True: "scan(s) with a negative range_min; read as 0 (a range of 0 or less is never a point)",
}


def _stamps_in_order(
    path: Path, scans: list[LaserScan], scan: str
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The scan stamps and where they step back in time (warned about once, kept in order)."""
    stamps = np.array([s.stamp for s in scans])
    back = np.diff(stamps) < 0
    if back.any():
        warn_once(
            log,
            path,
            f"{int(back.sum())} of {back.size} consecutive {printable(scan)} header stamps "
            f"go back in time (largest step back {float(-np.diff(stamps).min()):.3f} s); "
            "kept in bag order",
        )
    return stamps, back


def _sensor(info: dict[str, Any], s0: LaserScan, frame_id: str, scan_time: float) -> SensorInfo:
    """The sensor: geometry of the first scan, name and rate from our writer or the bag."""
    sensor_info = info.get("sensor") or {}
    rate = sensor_info.get("rate_hz")
    if rate is None and math.isfinite(scan_time) and scan_time > 0:
        rate = 1.0 / scan_time
    return SensorInfo(
        name=str(sensor_info.get("name") or frame_id or "unknown"),
        n_beams=s0.n_beams,
        angle_min=s0.angle_min,
        angle_increment=s0.angle_increment,
        range_min=s0.range_min,
        range_max=s0.range_max,
        rate_hz=rate,
    )
