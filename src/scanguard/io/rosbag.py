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

from scanguard.errors import FormatError, InputError, ScanError
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
        raise InputError(path, f"cannot write stamp {stamp} to a bag (must be finite, >= 0)")
    # Split before scaling: stamp * 1e9 would round away the last bits of epoch stamps.
    sec = math.floor(stamp)
    nanosec = round((stamp - sec) * 1e9)
    if nanosec >= 10**9:
        sec, nanosec = sec + 1, nanosec - 10**9
    return typestore.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nanosec))


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
        InputError: The sequence is empty, a stamp cannot be written, or ``path`` is an
            existing folder that is not a bag.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    dest = Path(path)
    if len(seq) == 0:
        raise InputError(dest, f"sequence {seq.name!r} has no scans to write")
    if dest.is_dir() and not (dest / "metadata.yaml").is_file():
        raise InputError(dest, "exists and is not a ROS 2 bag folder; not overwriting")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Header = T["std_msgs/msg/Header"]
    Pose, Point, Quat = (
        T["geometry_msgs/msg/Pose"],
        T["geometry_msgs/msg/Point"],
        T["geometry_msgs/msg/Quaternion"],
    )
    frame = str(seq.metadata.get("frame_id") or "laser")
    rate = seq.sensor.rate_hz if seq.sensor is not None else None
    scan_time = 1.0 / rate if rate else 0.0

    def odometry_msg(stamp: Any, parent: str, pose: NDArray[np.float64]) -> Any:
        qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(pose[2]))
        return T[ODOMETRY](
            header=Header(stamp=stamp, frame_id=parent),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=Pose(
                    position=Point(x=float(pose[0]), y=float(pose[1]), z=0.0),
                    orientation=Quat(x=qx, y=qy, z=qz, w=qw),
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

    info = {
        "name": seq.name,
        "scan_topic": scan_topic,
        "odom_topic": odom_topic if seq.odometry is not None else None,
        "reference_topic": reference_topic if seq.reference is not None else None,
        "reference_kind": seq.reference_kind,
        "laser_offset": seq.laser_offset.tolist(),
        "sensor": None
        if seq.sensor is None
        else {"name": seq.sensor.name, "rate_hz": seq.sensor.rate_hz},
        "metadata": {k: v for k, v in seq.metadata.items() if k not in ("topics", "path")},
    }
    info_json = json.dumps(info, default=_jsonable)

    dest.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    try:
        bagdir = tmpdir / (dest.stem if dest.suffix == ".mcap" else dest.name)
        with Writer(bagdir, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            c_info = writer.add_connection(INFO_TOPIC, "std_msgs/msg/String", typestore=ts)
            c_tf = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
            c_scan = writer.add_connection(scan_topic, LASERSCAN, typestore=ts)
            c_odom = (
                writer.add_connection(odom_topic, ODOMETRY, typestore=ts)
                if seq.odometry is not None
                else None
            )
            c_ref = (
                writer.add_connection(reference_topic, ODOMETRY, typestore=ts)
                if seq.reference is not None
                else None
            )
            t0 = _time(ts, seq.scans[0].stamp, dest)
            t0_ns = t0.sec * 10**9 + t0.nanosec
            writer.write(
                c_info,
                t0_ns,
                ts.serialize_cdr(T["std_msgs/msg/String"](data=info_json), "std_msgs/msg/String"),
            )
            off = seq.laser_offset
            qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(off[2]))
            tf = T["geometry_msgs/msg/TransformStamped"](
                header=Header(stamp=t0, frame_id="base_link"),
                child_frame_id=frame,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](
                        x=float(off[0]), y=float(off[1]), z=0.0
                    ),
                    rotation=Quat(x=qx, y=qy, z=qz, w=qw),
                ),
            )
            writer.write(
                c_tf,
                t0_ns,
                ts.serialize_cdr(
                    T["tf2_msgs/msg/TFMessage"](transforms=[tf]), "tf2_msgs/msg/TFMessage"
                ),
            )
            empty = np.zeros(0, dtype=np.float32)
            for i, s in enumerate(seq.scans):
                stamp = _time(ts, s.stamp, dest)
                ns = stamp.sec * 10**9 + stamp.nanosec
                msg = T[LASERSCAN](
                    header=Header(stamp=stamp, frame_id=frame),
                    angle_min=float(s.angle_min),
                    angle_max=float(s.angle_max),
                    angle_increment=float(s.angle_increment),
                    time_increment=0.0,
                    scan_time=scan_time,
                    range_min=float(s.range_min),
                    range_max=float(s.range_max),
                    ranges=s.ranges,
                    intensities=s.intensities if s.intensities is not None else empty,
                )
                writer.write(c_scan, ns, ts.serialize_cdr(msg, LASERSCAN))
                if c_odom is not None and seq.odometry is not None:
                    m = odometry_msg(stamp, "odom", seq.odometry[i])
                    writer.write(c_odom, ns, ts.serialize_cdr(m, ODOMETRY))
                if c_ref is not None and seq.reference is not None:
                    m = odometry_msg(stamp, "map", seq.reference[i])
                    writer.write(c_ref, ns, ts.serialize_cdr(m, ODOMETRY))
        if dest.suffix == ".mcap":
            os.replace(bagdir / f"{bagdir.name}.mcap", dest)
        else:
            old = None
            if dest.exists():
                old = tmpdir / "replaced"
                os.replace(dest, old)
            os.replace(bagdir, dest)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmpdir)
    log.info("wrote %d scans to %s", len(seq), dest)
    return dest
