"""Outputs of a simulation: destination checks before simulating, and a streaming bag writer.

`check_bag_output` accepts what ``scanguard simulate -o`` documents, a ``*.mcap`` file or a
ROS 2 bag folder (a name without an extension), and rejects anything else (``out.txt``, a
device, a FIFO, a folder that is not a bag, an unwritable place) before any simulation runs.

`BagStreamWriter` writes the scans to the bag while they are simulated (a `ScanSink` for
`simulate_run`), so a run of any length needs constant memory. It writes the same messages
as `scanguard.io.write_sequence` (the same bytes for the same sequence), under a temporary
name in the destination's folder, and renames the result into place only when the run
completed: a failed or interrupted run leaves no half-written bag, and temporaries left by
a killed process are removed by the next write to the same place.
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
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import OutputError
from scanguard.fsutil import _tmp_prefix, check_output_path, clean_stale_temporaries
from scanguard.geometry import yaw_to_quaternion
from scanguard.io.rosbag import INFO_TOPIC, LASERSCAN, ODOMETRY
from scanguard.scan import LaserScan, ScanSequence
from scanguard.sim.limits import format_bytes

log = logging.getLogger(__name__)

__all__ = [
    "BAG_SUFFIX",
    "PREVIEW_SUFFIX",
    "BagStreamWriter",
    "check_bag_output",
    "check_free_space",
    "check_preview_output",
]

#: Extension of a standalone MCAP bag file (any other output is a bag folder without one).
BAG_SUFFIX = ".mcap"
#: Extension of the preview image.
PREVIEW_SUFFIX = ".png"


def check_bag_output(path: str | Path) -> Path:
    """Check a bag destination before simulating; return the path to write to.

    Args:
        path: ``*.mcap`` (one MCAP file) or a name without an extension (a ROS 2 bag
            folder). An existing MCAP file or bag folder there is replaced when the new one
            is complete; a symbolic link is followed.

    Returns:
        The resolved destination (links followed, absolute).

    Raises:
        OutputError: Another extension, a special file, a file where a folder is expected
            or the reverse, an existing folder that is not a ROS 2 bag, or no permission to
            write there.
    """
    given = Path(path)
    if given.name in ("", ".", ".."):
        raise OutputError(given, "give the bag a name: NAME.mcap or a new folder NAME")
    suffix = given.suffix.lower()
    if suffix not in (BAG_SUFFIX, ""):
        raise OutputError(
            given,
            f"unsupported extension {given.suffix!r}: write a {BAG_SUFFIX} file or a ROS 2 bag "
            "folder (a name without an extension)",
        )
    if suffix == BAG_SUFFIX:
        return check_output_path(given, "file", suffixes=(BAG_SUFFIX,))
    real = check_output_path(given, "dir", suffixes=("",))
    if real.is_dir() and any(real.iterdir()) and not (real / "metadata.yaml").is_file():
        raise OutputError(given, "exists and is not a ROS 2 bag folder; not replacing it")
    return real


def check_preview_output(path: str | Path) -> Path:
    """Check a preview destination (a ``.png`` file) before simulating.

    Raises:
        OutputError: Another extension, a special file or folder there, or not writable.
    """
    return check_output_path(path, "file", suffixes=(PREVIEW_SUFFIX,))


def check_free_space(path: str | Path, need: float) -> None:
    """Check that the file system holding ``path`` has ``need`` bytes free.

    Raises:
        OutputError: Less space is free than needed.
    """
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        return  # cannot tell: the write itself reports a full disk
    if need > free:
        raise OutputError(
            path,
            f"the bag needs about {format_bytes(need)} but only {format_bytes(free)} are free "
            "there: lower --duration or write elsewhere",
        )


def _time(typestore: Any, stamp: float, path: Path) -> Any:
    if not math.isfinite(stamp) or stamp < 0:
        raise OutputError(path, f"cannot write stamp {stamp} to a bag (must be finite, >= 0)")
    # split before scaling: stamp * 1e9 would round away the last bits of epoch stamps
    sec = math.floor(stamp)
    nanosec = round((stamp - sec) * 1e9)
    if nanosec >= 10**9:
        sec, nanosec = sec + 1, nanosec - 10**9
    return typestore.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nanosec))


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


class BagStreamWriter:
    """Write a simulated run to a ROS 2 MCAP bag scan by scan (a `ScanSink`).

    Use it as a context manager around `simulate_run`: leaving the block normally moves the
    bag into place, leaving it with an exception (Ctrl-C included) removes everything it
    wrote. The temporary folder is made when the writer is created, so an unwritable
    destination fails before any simulation.

    Example:
        >>> with BagStreamWriter(check_bag_output("run.mcap")) as bag:  # doctest: +SKIP
        ...     simulate_run("lobby", seed=0, duration=60, sink=bag, keep_scans=False)

    Args:
        path: ``*.mcap`` for one MCAP file, anything else for a bag folder (check it with
            `check_bag_output` first).
        scan_topic: LaserScan topic.
        odom_topic: Odometry topic (frame ``odom``).
        reference_topic: Ground-truth topic (frame ``map``).

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
            self.tmpdir = Path(tempfile.mkdtemp(prefix=_tmp_prefix(self.path.name), dir=parent))
        except OSError as exc:
            self._remove_created()
            raise OutputError(self.path, f"cannot write there: {exc.strerror or exc}") from None
        is_mcap = self.path.suffix.lower() == BAG_SUFFIX
        self.bagdir = self.tmpdir / (self.path.stem if is_mcap else self.path.name)
        self.is_mcap = is_mcap

    # --- ScanSink ------------------------------------------------------------------------

    def begin(self, header: ScanSequence) -> None:
        """Open the bag: connections, the info message and the static transform.

        Args:
            header: The run's name, sensor, laser offset, reference kind and metadata (no
                scans).
        """
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        if self._writer is not None:
            raise RuntimeError("BagStreamWriter.begin called twice")
        scan_topic, odom_topic, reference_topic = self.topics
        ts = get_typestore(Stores.ROS2_HUMBLE)
        self._ts = ts
        T = ts.types
        self._frame = str(header.metadata.get("frame_id") or "laser")
        rate = header.sensor.rate_hz if header.sensor is not None else None
        self._scan_time = 1.0 / rate if rate else 0.0
        info = {
            "name": header.name,
            "scan_topic": scan_topic,
            "odom_topic": odom_topic,
            "reference_topic": reference_topic,
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
        self._c_odom = writer.add_connection(odom_topic, ODOMETRY, typestore=ts)
        self._c_ref = writer.add_connection(reference_topic, ODOMETRY, typestore=ts)
        self._T = T

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
        self, scan: LaserScan, reference: NDArray[np.float64], odometry: NDArray[np.float64]
    ) -> None:
        """Write one scan with its odometry and ground-truth poses."""
        if self._writer is None:
            raise RuntimeError("BagStreamWriter.add called before begin")
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
        odo = self._odometry_msg(stamp, "odom", odometry)
        self._write(self._c_odom, ns, ts.serialize_cdr(odo, ODOMETRY))
        ref = self._odometry_msg(stamp, "map", reference)
        self._write(self._c_ref, ns, ts.serialize_cdr(ref, ODOMETRY))
        self.count += 1

    # --- commit / abort ------------------------------------------------------------------

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

    def __enter__(self) -> BagStreamWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
