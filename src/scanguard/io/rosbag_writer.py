"""Write ROS 2 bags (MCAP storage) through `rosbags`: `write_rosbag` and `BagWriter`.

The result holds standard messages so rviz, Foxglove and ``ros2 bag`` open it:
``sensor_msgs/msg/LaserScan`` on the scan topic, ``nav_msgs/msg/Odometry`` for odometry (frame
``odom``) and for the reference (frame ``map``), ``tf2_msgs/msg/TFMessage`` on ``/tf_static``
(``base_link`` -> scan frame = laser offset) and one ``std_msgs/msg/String`` on
``/scanguard/info`` holding JSON (sequence name, sensor name, reference kind, topics,
metadata) so `scanguard.io.rosbag.RosbagReader` restores the sequence exactly.

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
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import InputError, OutputError
from scanguard.geometry import yaw_to_quaternion
from scanguard.io.rosbag import INFO_TOPIC, LASERSCAN, ODOMETRY
from scanguard.scan import LaserScan, ScanSequence

log = logging.getLogger(__name__)

__all__ = ["BagWriter", "write_rosbag"]


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
