"""ROS bags through `rosbags`: ROS 1 ``.bag``, ROS 2 bag folders, ``.db3`` and ``.mcap``.

Reading (`RosbagReader`) uses ``rosbags.highlevel.AnyReader``:

* scans come from one ``sensor_msgs/LaserScan`` topic, stamped with their header stamps;
* odometry (``nav_msgs/Odometry``) and the optional reference (``nav_msgs/Odometry``,
  ``geometry_msgs/PoseStamped`` or ``PoseWithCovarianceStamped``) are interpolated to the
  scan stamps;
* the laser offset comes from ``/tf_static`` (a transform whose child is the scan frame).

Accepted paths: a ROS 1 ``.bag``; a ROS 2 bag folder (with ``metadata.yaml``); the
``.mcap``/``.db3`` file inside such a folder (the folder is opened); a standalone ``.mcap``.

Writing (`write_rosbag`) produces standard messages so rviz, Foxglove and ``ros2 bag`` open
the result: ``sensor_msgs/msg/LaserScan`` on the scan topic, ``nav_msgs/msg/Odometry`` for
odometry (frame ``odom``) and for the reference (frame ``map``), ``tf2_msgs/msg/TFMessage``
on ``/tf_static`` (``base_link`` -> scan frame = laser offset) and one
``std_msgs/msg/String`` on ``/scanguard/info`` holding JSON (sequence name, sensor name,
reference kind, topics, metadata) so our reader restores the sequence exactly.

Output path mapping: ``rosbags`` writes bag *folders*. A path ending in ``.mcap`` becomes a
single standalone MCAP file at exactly that path (the folder is written in a temporary
directory next to it and its MCAP file is renamed into place; ``metadata.yaml`` is not
needed by MCAP readers). Any other path becomes a ROS 2 bag folder (MCAP storage), written
under a temporary name and renamed into place; an existing bag folder there is replaced.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, OutputError, ScanError
from scanguard.geometry import quaternion_to_yaw, yaw_to_quaternion
from scanguard.io.base import (
    LENIENT_HINT,
    MAX_NAMES,
    align_poses,
    bad_pose_rows,
    pose_problem,
    printable,
    warn_once,
)
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

log = logging.getLogger(__name__)

__all__ = ["INFO_TOPIC", "RosbagReader", "write_rosbag"]

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

        path = Path(path)
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
        topics: dict[str, dict[str, Any]] = {}
        conns_by_topic: dict[str, list[Any]] = {}
        for c in reader.connections:
            entry = topics.setdefault(c.topic, {"type": c.msgtype, "count": 0})
            entry["count"] += int(c.msgcount)
            conns_by_topic.setdefault(c.topic, []).append(c)
        by_norm = {_norm(t): t for t in topics}

        def found() -> str:
            names = [
                f"{printable(t)} ({printable(v['type'], 48)})" for t, v in sorted(topics.items())
            ]
            if len(names) > MAX_NAMES:
                names = [*names[:MAX_NAMES], f"and {len(names) - MAX_NAMES} more"]
            return ", ".join(names) or "none"

        def lookup(topic: str, allowed: tuple[str, ...], role: str) -> str:
            real = by_norm.get(_norm(topic))
            if real is None:
                raise InputError(
                    path,
                    f"no {role} topic {printable(topic)!r}; topics found: {found()}",
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

        info: dict[str, Any] = {}
        if INFO_TOPIC in topics and topics[INFO_TOPIC]["type"] == "std_msgs/msg/String":
            for c, _, raw in reader.messages(connections=conns_by_topic[INFO_TOPIC]):
                try:
                    info = json.loads(reader.deserialize(raw, c.msgtype).data)
                except json.JSONDecodeError as exc:
                    log.warning("%s: ignoring unreadable %s (%s)", path, INFO_TOPIC, exc)
                break

        # --- scan topic
        laser_topics = sorted(t for t, v in topics.items() if v["type"] == LASERSCAN)
        if scan_topic is not None:
            scan = lookup(scan_topic, (LASERSCAN,), "LaserScan")
        elif not laser_topics:
            raise InputError(path, f"no sensor_msgs/LaserScan topic; topics found: {found()}")
        elif len(laser_topics) == 1:
            scan = laser_topics[0]
        elif info.get("scan_topic") in laser_topics:
            scan = info["scan_topic"]
        else:
            raise InputError(
                path,
                f"several LaserScan topics ({', '.join(map(printable, laser_topics))}); "
                "choose one with --scan-topic",
            )

        # --- reference and odometry topics
        pose_topics = sorted(t for t, v in topics.items() if v["type"] in POSE_TYPES)
        ref: str | None = None
        if reference_topic is not None:
            ref = lookup(reference_topic, POSE_TYPES, "reference")
        elif info.get("reference_topic") in pose_topics:
            ref = info["reference_topic"]
        else:
            named = [t for t in pose_topics if _norm(t) in GROUND_TRUTH_NAMES]
            ref = named[0] if len(named) == 1 else None
        odom: str | None = None
        if odom_topic is not None:
            odom = lookup(odom_topic, POSE_TYPES, "odometry")
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

        # --- messages
        scans: list[LaserScan] = []
        frame_id = ""
        scan_time = 0.0
        poses: dict[str, tuple[list[float], list[tuple[float, float, float]]]] = {
            t: ([], []) for t in (odom, ref) if t is not None
        }
        statics: list[Any] = []
        skipped: list[str] = []

        def malformed(topic: str, what: str) -> None:
            if not self.lenient:
                raise FormatError(path, what + LENIENT_HINT, location=f"topic {printable(topic)}")
            skipped.append(f"topic {printable(topic)}: {what}")

        wanted = [scan, *poses]
        conns = [c for t in wanted for c in conns_by_topic[t]]
        conns += conns_by_topic.get("/tf_static", [])
        n_scan_msgs = 0
        for c, bag_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, c.msgtype)
            if c.topic == scan:
                stamp = _stamp(msg.header)
                if stamp == 0.0:
                    stamp = bag_ns * 1e-9  # some drivers leave header stamps empty
                try:
                    scans.append(
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
                    malformed(scan, f"message {n_scan_msgs}: {exc}")
                n_scan_msgs += 1
                if not frame_id:
                    frame_id = msg.header.frame_id
                    scan_time = float(msg.scan_time)
            elif c.topic in poses:
                stamp = _stamp(msg.header)
                pose = _pose_of(msg)
                if bad_pose_rows(np.array(pose))[0]:
                    k = len(poses[c.topic][0])
                    malformed(c.topic, f"message {k}: {pose_problem(np.array(pose))}")
                    continue
                poses[c.topic][0].append(stamp if stamp != 0.0 else bag_ns * 1e-9)
                poses[c.topic][1].append(pose)
            elif c.msgtype == "tf2_msgs/msg/TFMessage":
                statics.extend(msg.transforms)
        if skipped:
            warn_once(
                log,
                path,
                f"lenient read: skipped {len(skipped)} malformed message(s) (first: {skipped[0]})",
            )
        if not scans:
            what = "has no usable messages" if skipped else "has no messages"
            raise InputError(path, f"LaserScan topic {what}", location=f"topic {printable(scan)}")

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

        def aligned(topic: str | None) -> NDArray[np.float64] | None:
            if topic is None:
                return None
            t, p = poses[topic]
            return align_poses(
                path, f"topic {topic}", np.array(t), np.array(p, dtype=np.float64), stamps
            )

        odometry = aligned(odom)
        reference = aligned(ref)

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

        s0 = scans[0]
        sensor_info = info.get("sensor") or {}
        rate = sensor_info.get("rate_hz")
        if rate is None and math.isfinite(scan_time) and scan_time > 0:
            rate = 1.0 / scan_time
        sensor = SensorInfo(
            name=str(sensor_info.get("name") or frame_id or "unknown"),
            n_beams=s0.n_beams,
            angle_min=s0.angle_min,
            angle_increment=s0.angle_increment,
            range_min=s0.range_min,
            range_max=s0.range_max,
            rate_hz=rate,
        )
        metadata: dict[str, Any] = dict(info.get("metadata") or {})
        # a sequence we wrote keeps its own "source" (e.g. "scanguard.sim"); "path" is the file
        metadata.setdefault("source", str(path))
        metadata.update(
            {
                "format": self.name,
                "path": str(path),
                "scan_topic": scan,
                "frame_id": frame_id,
                "topics": topics,
            }
        )
        if back.any():
            metadata["stamps_not_increasing"] = int(back.sum())
        if skipped:
            metadata["skipped_lines"] = len(skipped)
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
            sensor=sensor,
            odometry=odometry,
            reference=reference,
            reference_kind=reference_kind,
            laser_offset=laser_offset,
            metadata=metadata,
        )


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return str(value)


def _time(typestore: Any, stamp: float, path: Path) -> Any:
    if not math.isfinite(stamp) or stamp < 0:
        raise OutputError(path, f"cannot write stamp {stamp} to a bag (must be finite, >= 0)")
    # Split before scaling: stamp * 1e9 would round away the last bits of epoch stamps.
    sec = math.floor(stamp)
    nanosec = round((stamp - sec) * 1e9)
    if nanosec >= 10**9:
        sec, nanosec = sec + 1, nanosec - 10**9
    return typestore.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nanosec))


class BagWriter:
    """Write a ROS 2 MCAP bag scan by scan, atomically (see the module docstring).

    `begin` once with a header sequence (name, sensor, laser offset, reference kind, metadata;
    its scans are not used), then `add` for every scan, in order. Used as a context manager,
    leaving the block normally finishes the bag and moves it into place; leaving it with an
    exception (Ctrl-C included) removes everything written. The temporary folder is made when
    the writer is created, so an unwritable destination fails before any work, and
    temporaries left by a killed process are removed by the next write to the same place.
    `write_rosbag` (whole sequences) and the simulator's streaming output share this writer.

    Args:
        path: ``*.mcap`` for one MCAP file, anything else for a bag folder.
        scan_topic: LaserScan topic.
        odom_topic: Odometry topic (frame ``odom``).
        reference_topic: Reference topic (frame ``map``).

    Raises:
        OutputError: The destination's folder cannot be made or written.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        scan_topic: str = "/scan",
        odom_topic: str = "/odom",
        reference_topic: str = "/ground_truth",
    ) -> None:
        from scanguard.fsutil import clean_stale_temporaries, temporary_prefix

        self.path = Path(path)
        self.topics = (scan_topic, odom_topic, reference_topic)
        self.count = 0
        self._writer: Any = None
        self._created: list[Path] = []
        parent = self.path.parent
        p = parent
        while not p.exists() and p != p.parent:
            self._created.append(p)
            p = p.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            clean_stale_temporaries(parent, self.path.name)
            self.tmpdir = Path(
                tempfile.mkdtemp(prefix=temporary_prefix(self.path.name), dir=parent)
            )
        except OSError as exc:
            self._remove_created()
            raise OutputError(self.path, f"cannot write there: {exc.strerror or exc}") from None
        self.is_mcap = self.path.suffix.lower() == ".mcap"
        self.bagdir = self.tmpdir / (self.path.stem if self.is_mcap else self.path.name)

    def begin(self, header: ScanSequence, *, odometry: bool = True, reference: bool = True) -> None:
        """Open the bag: connections and the info message's content.

        Args:
            header: The recording's name, sensor, laser offset, reference kind and metadata.
            odometry: Write an odometry topic.
            reference: Write a reference topic.
        """
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        if self._writer is not None:
            raise RuntimeError("BagWriter.begin called twice")
        scan_topic, odom_topic, reference_topic = self.topics
        ts = get_typestore(Stores.ROS2_HUMBLE)
        self._ts, self._T = ts, ts.types
        self._frame = str(header.metadata.get("frame_id") or "laser")
        rate = header.sensor.rate_hz if header.sensor is not None else None
        self._scan_time = 1.0 / rate if rate else 0.0
        info = {
            "name": header.name,
            "scan_topic": scan_topic,
            "odom_topic": odom_topic if odometry else None,
            "reference_topic": reference_topic if reference else None,
            "reference_kind": header.reference_kind,
            "laser_offset": header.laser_offset.tolist(),
            "sensor": None
            if header.sensor is None
            else {"name": header.sensor.name, "rate_hz": header.sensor.rate_hz},
            "metadata": {k: v for k, v in header.metadata.items() if k not in ("topics", "path")},
        }
        self._info_json = json.dumps(info, default=_jsonable)
        self._laser_offset = header.laser_offset
        try:
            writer = Writer(self.bagdir, version=9, storage_plugin=StoragePlugin.MCAP)
            writer.open()
        except OSError as exc:
            raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") from None
        self._writer = writer
        self._c_info = writer.add_connection(INFO_TOPIC, "std_msgs/msg/String", typestore=ts)
        self._c_tf = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        self._c_scan = writer.add_connection(scan_topic, LASERSCAN, typestore=ts)
        self._c_odom = (
            writer.add_connection(odom_topic, ODOMETRY, typestore=ts) if odometry else None
        )
        self._c_ref = (
            writer.add_connection(reference_topic, ODOMETRY, typestore=ts) if reference else None
        )

    def _header_messages(self, first_stamp: float) -> None:
        ts, T = self._ts, self._T
        t0 = _time(ts, first_stamp, self.path)
        t0_ns = t0.sec * 10**9 + t0.nanosec
        self._write(
            self._c_info,
            t0_ns,
            ts.serialize_cdr(T["std_msgs/msg/String"](data=self._info_json), "std_msgs/msg/String"),
        )
        off = self._laser_offset
        qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(off[2]))
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=t0, frame_id="base_link"),
            child_frame_id=self._frame,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(off[0]), y=float(off[1]), z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
            ),
        )
        self._write(
            self._c_tf,
            t0_ns,
            ts.serialize_cdr(
                T["tf2_msgs/msg/TFMessage"](transforms=[tf]), "tf2_msgs/msg/TFMessage"
            ),
        )

    def _odometry_msg(self, stamp: Any, parent: str, pose: NDArray[np.float64]) -> Any:
        T = self._T
        qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(pose[2]))
        return T[ODOMETRY](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=parent),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](
                        x=float(pose[0]), y=float(pose[1]), z=0.0
                    ),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
                covariance=np.zeros(36),
            ),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                ),
                covariance=np.zeros(36),
            ),
        )

    def _write(self, connection: Any, ns: int, data: Any) -> None:
        try:
            self._writer.write(connection, ns, data)
        except OSError as exc:
            raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") from None

    def add(
        self,
        scan: LaserScan,
        reference: NDArray[np.float64] | None = None,
        odometry: NDArray[np.float64] | None = None,
    ) -> None:
        """Write one scan with its reference and odometry poses (each where its topic is)."""
        if self._writer is None:
            raise RuntimeError("BagWriter.add called before begin")
        if self.count == 0:
            self._header_messages(scan.stamp)
        ts, T = self._ts, self._T
        stamp = _time(ts, scan.stamp, self.path)
        ns = stamp.sec * 10**9 + stamp.nanosec
        msg = T[LASERSCAN](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=self._frame),
            angle_min=float(scan.angle_min),
            angle_max=float(scan.angle_max),
            angle_increment=float(scan.angle_increment),
            time_increment=0.0,
            scan_time=self._scan_time,
            range_min=float(scan.range_min),
            range_max=float(scan.range_max),
            ranges=scan.ranges,
            intensities=scan.intensities
            if scan.intensities is not None
            else np.zeros(0, dtype=np.float32),
        )
        self._write(self._c_scan, ns, ts.serialize_cdr(msg, LASERSCAN))
        if self._c_odom is not None and odometry is not None:
            odo = self._odometry_msg(stamp, "odom", odometry)
            self._write(self._c_odom, ns, ts.serialize_cdr(odo, ODOMETRY))
        if self._c_ref is not None and reference is not None:
            ref = self._odometry_msg(stamp, "map", reference)
            self._write(self._c_ref, ns, ts.serialize_cdr(ref, ODOMETRY))
        self.count += 1

    def close(self) -> Path:
        """Finish the bag and move it into place.

        Returns:
            The written path.

        Raises:
            OutputError: No scan was written, or the bag cannot be finished or moved.
        """
        if self._writer is None or self.count == 0:
            self.abort()
            raise OutputError(self.path, "no scans to write")
        dest = self.path
        try:
            self._writer.close()
            self._writer = None
            if self.is_mcap:
                os.replace(self.bagdir / f"{self.bagdir.name}.mcap", dest)
            else:
                if os.path.lexists(dest):
                    os.replace(dest, self.tmpdir / "replaced")
                os.replace(self.bagdir, dest)
        except OSError as exc:
            self.abort()
            raise OutputError(dest, f"cannot write: {exc.strerror or exc}") from None
        with contextlib.suppress(OSError):
            shutil.rmtree(self.tmpdir)
        log.info("wrote %d scans to %s", self.count, dest)
        return dest

    def abort(self) -> None:
        """Remove everything written so far (the destination is left as it was)."""
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()
            self._writer = None
        with contextlib.suppress(OSError):
            shutil.rmtree(self.tmpdir)
        self._remove_created()

    def _remove_created(self) -> None:
        for folder in self._created:  # innermost first; only while still empty
            with contextlib.suppress(OSError):
                folder.rmdir()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_rosbag(
    seq: ScanSequence,
    path: str | Path,
    *,
    scan_topic: str = "/scan",
    odom_topic: str = "/odom",
    reference_topic: str = "/ground_truth",
) -> Path:
    """Write a sequence as a ROS 2 bag with MCAP storage (see the module docstring).

    Args:
        seq: The sequence.
        path: ``*.mcap`` for a standalone MCAP file, anything else for a bag folder.
        scan_topic: LaserScan topic.
        odom_topic: Odometry topic (written only if the sequence has odometry).
        reference_topic: Reference topic (written only if it has reference poses).

    Returns:
        The written path.

    Raises:
        InputError: The sequence is empty, or ``path`` is an existing folder that is not a
            bag.
        OutputError: A stamp cannot be written, or the destination cannot be written.
    """
    dest = Path(path)
    if len(seq) == 0:
        raise InputError(dest, f"sequence {seq.name!r} has no scans to write")
    if dest.is_dir() and not (dest / "metadata.yaml").is_file():
        raise InputError(dest, "exists and is not a ROS 2 bag folder; not overwriting")
    with BagWriter(
        dest, scan_topic=scan_topic, odom_topic=odom_topic, reference_topic=reference_topic
    ) as bag:
        bag.begin(seq, odometry=seq.odometry is not None, reference=seq.reference is not None)
        for i, scan in enumerate(seq.scans):
            bag.add(
                scan,
                None if seq.reference is None else seq.reference[i],
                None if seq.odometry is None else seq.odometry[i],
            )
    return dest
