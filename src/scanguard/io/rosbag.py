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

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, ScanError
from scanguard.geometry import quaternion_to_yaw
from scanguard.io.base import (
    LENIENT_HINT,
    MAX_NAMES,
    align_poses,
    bad_pose_rows,
    check_recording_path,
    pose_problem,
    printable,
    warn_once,
)
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

log = logging.getLogger(__name__)

__all__ = ["INFO_TOPIC", "RosbagReader"]

INFO_TOPIC = "/scanguard/info"
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


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def _pose_of(msg: Any) -> tuple[float, float, float]:
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    q = pose.orientation
    yaw = float(quaternion_to_yaw(np.array([q.x, q.y, q.z, q.w])))
    return float(pose.position.x), float(pose.position.y), yaw


def _resolve_bag_path(path: Path) -> Path:
    if not path.exists():
        raise InputError(path, "file not found")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path
        storages = sorted([*path.glob("*.mcap"), *path.glob("*.db3")])
        if len(storages) == 1:
            return storages[0]
        raise InputError(
            path, "folder is not a ROS 2 bag (no metadata.yaml and not exactly one .mcap/.db3)"
        )
    if path.suffix in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


@dataclass
class RosbagReader:
    """Reader for ROS 1 and ROS 2 bags (see the module docstring).

    Malformed messages (a scan with zero beams, a non-finite angle or a field of view outside
    (0, 360] degrees; a pose that is not finite or beyond 1e6 m) are errors naming the bag,
    the topic and the message.

    Attributes:
        lenient: Skip malformed messages instead (one warning gives their count).
    """

    lenient: bool = False
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
        errors = (AnyReaderError, Reader1Error, Reader2Error, KeyError, ValueError, EOFError)
        try:
            with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
                return self._read_open(path, reader, scan_topic, odom_topic, reference_topic)
        except errors as exc:
            raise FormatError(
                path, f"cannot read bag ({type(exc).__name__}: {printable(str(exc), 160)})"
            ) from None
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
        info = _read_info(path, reader, index)
        scan = _choose_scan(index, info, scan_topic)
        ref, odom = _choose_pose_topics(index, info, odom_topic, reference_topic)
        poses: dict[str, tuple[list[float], list[tuple[float, float, float]]]] = {
            t: ([], []) for t in (odom, ref) if t is not None
        }
        msgs = _Messages(path, self.lenient, scan, poses)
        msgs.read(reader, index)
        scans = msgs.scans
        stamps, back = _stamps_in_order(path, scans, scan)
        odometry = msgs.aligned(odom, stamps)
        reference = msgs.aligned(ref, stamps)
        laser_offset = _laser_offset(info, msgs.statics, msgs.frame_id)
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
        if msgs.skipped:
            metadata["skipped_lines"] = len(msgs.skipped)
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
        if topics[real]["type"] not in allowed:
            raise InputError(
                path,
                f"{role} topic has type {printable(topics[real]['type'], 48)}, expected "
                f"{' or '.join(allowed)}",
                location=f"topic {printable(real)}",
            )
        return real


def _read_info(path: Path, reader: Any, index: _TopicIndex) -> dict[str, Any]:
    """The JSON of our writer's info message (empty if the bag has none)."""
    info: dict[str, Any] = {}
    topics = index.topics
    if INFO_TOPIC in topics and topics[INFO_TOPIC]["type"] == "std_msgs/msg/String":
        for c, _, raw in reader.messages(connections=index.conns_by_topic[INFO_TOPIC]):
            try:
                info = json.loads(reader.deserialize(raw, c.msgtype).data)
            except json.JSONDecodeError as exc:
                log.warning("%s: ignoring unreadable %s (%s)", path, INFO_TOPIC, exc)
            break
    return info


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

    def malformed(self, topic: str, what: str) -> None:
        """Raise `FormatError` for a malformed message, or (lenient) note it as skipped."""
        if not self.lenient:
            raise FormatError(self.path, what + LENIENT_HINT, location=f"topic {printable(topic)}")
        self.skipped.append(f"topic {printable(topic)}: {what}")

    def read(self, reader: Any, index: _TopicIndex) -> None:
        """Read the scan and pose topics and ``/tf_static``; `InputError` if no scan is usable."""
        path, scan = self.path, self.scan
        wanted = [scan, *self.poses]
        conns = [c for t in wanted for c in index.conns_by_topic[t]]
        conns += index.conns_by_topic.get("/tf_static", [])
        for c, bag_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, c.msgtype)
            if c.topic == scan:
                self._add_scan(msg, bag_ns)
            elif c.topic in self.poses:
                self._add_pose(c.topic, msg, bag_ns)
            elif c.msgtype == "tf2_msgs/msg/TFMessage":
                self.statics.extend(msg.transforms)
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

    def _add_scan(self, msg: Any, bag_ns: int) -> None:
        stamp = _stamp(msg.header)
        if stamp == 0.0:
            stamp = bag_ns * 1e-9  # some drivers leave header stamps empty
        try:
            self.scans.append(
                LaserScan(
                    stamp=stamp,
                    ranges=np.asarray(msg.ranges, dtype=np.float32),
                    angle_min=float(msg.angle_min),
                    angle_increment=float(msg.angle_increment),
                    range_min=float(msg.range_min),
                    range_max=float(msg.range_max),
                    intensities=np.asarray(msg.intensities, dtype=np.float32),
                )
            )
        except ScanError as exc:
            self.malformed(self.scan, f"message {self.n_scan_msgs}: {exc}")
        self.n_scan_msgs += 1
        if not self.frame_id:
            self.frame_id = msg.header.frame_id
            self.scan_time = float(msg.scan_time)

    def _add_pose(self, topic: str, msg: Any, bag_ns: int) -> None:
        stamp = _stamp(msg.header)
        pose = _pose_of(msg)
        if bad_pose_rows(np.array(pose))[0]:
            k = len(self.poses[topic][0])
            self.malformed(topic, f"message {k}: {pose_problem(np.array(pose))}")
            return
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


def _laser_offset(info: dict[str, Any], statics: list[Any], frame_id: str) -> NDArray[np.float64]:
    """The laser offset: our writer's, else the static transform to the scan frame, else 0."""
    laser_offset = np.zeros(3)
    if info.get("laser_offset") is not None:
        laser_offset = np.asarray(info["laser_offset"], dtype=np.float64)
    else:
        for tf in statics:
            if _norm(tf.child_frame_id) == _norm(frame_id) and frame_id:
                tr, q = tf.transform.translation, tf.transform.rotation
                yaw = float(quaternion_to_yaw(np.array([q.x, q.y, q.z, q.w])))
                laser_offset = np.array([tr.x, tr.y, yaw])
                break
    return laser_offset


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
