"""The messages of a run's view (``result.mcap``, the live view): ROS 2 CDR and JSON.

Every message is encoded once, to bytes, and handed to every output (`scanguard.apps.viz_sink`):
the MCAP file and the Foxglove WebSocket server log the same bytes. ROS 2 messages are
serialised by `rosbags` (the typestore the recording readers and writers already use), with
their ``ros2msg`` schema text, so that ``ros2 bag play`` and rviz2 read the file as it is; the
guard's decision has no ROS equivalent and is JSON with a JSON schema (Foxglove plots its
numeric fields as time series).
"""

from __future__ import annotations

import io
import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import InputError
from scanguard.geometry import yaw_to_quaternion
from scanguard.scan import LaserScan

#: Schema encoding of ROS 2 message definitions in MCAP (and the Foxglove WS protocol).
ROS2MSG = "ros2msg"
#: Message encoding of ROS 2 messages.
CDR = "cdr"

LASERSCAN = "sensor_msgs/msg/LaserScan"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
PATH = "nav_msgs/msg/Path"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"

#: Values of `nav_msgs/OccupancyGrid` cells (ROS ``map_server``'s trinary mode).
GRID_OCCUPIED, GRID_FREE, GRID_UNKNOWN = 100, 0, -1

#: JSON schema of the guard's decision on one scan (``/scanguard/decision``).
DECISION_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "scanguard.Decision",
    "properties": {
        "index": {"type": "integer", "description": "scan index"},
        "stamp": {"type": "number", "description": "scan stamp (s)"},
        "fault_probability": {"type": ["number", "null"], "description": "CNN"},
        "baseline_score": {"type": ["number", "null"], "description": "classical score"},
        "accepted": {"type": "boolean", "description": "the guard's policy accepted it"},
        "verdict": {"type": "string", "enum": ["accepted", "rejected", "failed", "skipped"]},
        "reason": {"type": "string"},
        "reference_label": {"type": ["integer", "null"], "description": "1 = fault"},
        "odom_trans_z": {"type": ["number", "null"], "description": "match vs odometry (sigma)"},
        "odom_rot_z": {"type": ["number", "null"], "description": "match vs odometry (sigma)"},
        "motion_sources": {
            "type": ["string", "null"],
            "description": "fused motion of the main instance: wheels, match, prediction",
        },
        "wheels_flagged": {
            "type": ["boolean", "null"],
            "description": "a normal match disagreed with the wheels beyond their noise",
        },
        "instances": {
            "type": "object",
            "description": "instance -> its gate accepted the scan",
            "additionalProperties": {"type": "boolean"},
        },
    },
}


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: topic, schema and message encoding.

    Attributes:
        topic: Topic name.
        schema_name: ``sensor_msgs/msg/LaserScan``, ``scanguard.Decision``...
        schema_encoding: ``ros2msg`` or ``jsonschema``.
        schema: The schema's text (ROS 2 definition with its dependencies, or JSON schema).
        encoding: Message encoding, ``cdr`` or ``json``.
    """

    topic: str
    schema_name: str
    schema_encoding: str
    schema: bytes
    encoding: str


def stamp_ns(stamp: float) -> int:
    """Nanoseconds of a stamp in seconds (negative or non-finite stamps become 0).

    The seconds are split before scaling: ``stamp * 1e9`` would round away the last bits of
    an epoch stamp.
    """
    if not math.isfinite(stamp) or stamp < 0:
        return 0
    sec = math.floor(stamp)
    return int(sec) * 10**9 + min(round((stamp - sec) * 1e9), 10**9 - 1)


#: Largest stamp (s) a ROS 2 ``builtin_interfaces/Time`` holds: its ``sec`` is an int32.
MAX_ROS_STAMP = 2**31 - 1


def check_ros_stamps(stamps: NDArray[np.float64], source: str) -> None:
    """Refuse stamps that ROS time cannot hold, before any message is written.

    A negative stamp became time 0 (every message of such a recording at one instant) and a
    stamp past `MAX_ROS_STAMP` failed in the middle of a run with ``struct.error``.

    Raises:
        InputError: A stamp is negative or beyond `MAX_ROS_STAMP`; names ``source``.
    """
    t = np.asarray(stamps, dtype=np.float64)
    if not t.size:
        return
    lo, hi = float(np.min(t)), float(np.max(t))
    if lo >= 0 and hi <= MAX_ROS_STAMP:
        return
    bad = f"start at {lo:.9g} s (negative)" if lo < 0 else f"reach {hi:.9g} s"
    raise InputError(
        source,
        f"scan stamps {bad}: ROS time holds 0 to {MAX_ROS_STAMP} s, so --mcap/--live cannot "
        "show them; shift the recording's clock or run without a view",
    )


def grid_cells(grid: Any) -> NDArray[np.int8]:
    """`OccupancyGrid` cells as ROS values, row 0 = lowest ``y`` (the PGM's cells, unflipped)."""
    p = grid.probability()
    cells = np.full(p.shape, GRID_UNKNOWN, dtype=np.int8)
    cells[p > grid.config.occupied_thresh] = GRID_OCCUPIED
    cells[p < grid.config.free_thresh] = GRID_FREE
    return cells


def png_bytes(image: NDArray[np.uint8]) -> bytes:
    """PNG of an ``(H, W, 3)`` or ``(H, W)`` uint8 image."""
    from PIL import Image

    buf = io.BytesIO()
    # fastest zlib level: the rendered pairs are mostly flat background and compress anyway
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def json_bytes(obj: Any) -> bytes:
    """Strict JSON (non-finite numbers become null)."""

    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, float) and not math.isfinite(v):
            return None
        return v

    return json.dumps(clean(obj), allow_nan=False).encode()


#: One ``geometry_msgs/PoseStamped`` in frame ``map`` as packed little-endian CDR: the
#: header (stamp, frame_id ``"map"``) and the pose (position, orientation: 7 float64).
_POSE_STAMPED = np.dtype(
    [
        ("sec", "<i4"),
        ("nanosec", "<u4"),
        ("frame_len", "<u4"),
        ("frame", "S4"),
        ("x", "<f8"),
        ("y", "<f8"),
        ("z", "<f8"),
        ("qx", "<f8"),
        ("qy", "<f8"),
        ("qz", "<f8"),
        ("qw", "<f8"),
    ]
)
_POSE_HEADER = 16  # bytes of the header part (stamp, frame_id) of `_POSE_STAMPED`
_POSE_SIZE = _POSE_STAMPED.itemsize


class Encoder:
    """Builds the ROS 2 messages of the view, serialised to CDR by `rosbags`."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T = self.ts.types

    def ros_channel(self, topic: str, typename: str) -> ChannelSpec:
        """The channel of a ROS 2 message type, with its full definition as the schema."""
        text, _ = self.ts.generate_msgdef(typename, ros_version=2)
        return ChannelSpec(topic, typename, ROS2MSG, text.encode(), CDR)

    @staticmethod
    def json_channel(topic: str, name: str, schema: dict[str, Any]) -> ChannelSpec:
        """A JSON channel with a JSON schema."""
        return ChannelSpec(topic, name, "jsonschema", json.dumps(schema).encode(), "json")

    def _header(self, ns: int, frame: str) -> Any:
        T = self.T
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def _pose(self, pose: NDArray[np.float64]) -> Any:
        T = self.T
        qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(float(pose[2])))
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(pose[0]), y=float(pose[1]), z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )

    def laser_scan(self, scan: LaserScan, ns: int, frame: str) -> bytes:
        """``sensor_msgs/LaserScan`` of one scan."""
        msg = self.T[LASERSCAN](
            header=self._header(ns, frame),
            angle_min=float(scan.angle_min),
            angle_max=float(scan.angle_max),
            angle_increment=float(scan.angle_increment),
            time_increment=0.0,
            scan_time=0.0,
            range_min=float(scan.range_min),
            range_max=float(scan.range_max),
            ranges=np.asarray(scan.ranges, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32)
            if scan.intensities is None
            else np.asarray(scan.intensities, dtype=np.float32),
        )
        return bytes(self.ts.serialize_cdr(msg, LASERSCAN))

    def occupancy_grid(self, grid: Any, ns: int, frame: str = "map") -> bytes:
        """``nav_msgs/OccupancyGrid`` of an `OccupancyGrid` (cells as in its PGM)."""
        T = self.T
        cells = grid_cells(grid)
        header = self._header(ns, frame)
        origin = np.array([grid.origin[0], grid.origin[1], 0.0])
        msg = T[OCCUPANCY_GRID](
            header=header,
            info=T["nav_msgs/msg/MapMetaData"](
                map_load_time=header.stamp,
                resolution=float(grid.resolution),
                width=int(cells.shape[1]),
                height=int(cells.shape[0]),
                origin=self._pose(origin),
            ),
            data=cells.reshape(-1),
        )
        return bytes(self.ts.serialize_cdr(msg, OCCUPANCY_GRID))

    def path(self, stamps: NDArray[np.float64], poses: NDArray[np.float64], ns: int) -> bytes:
        """``nav_msgs/Path`` of robot poses ``(N, 3)`` in the map frame (non-finite ones left out).

        The poses are packed by numpy, not built as N message objects: a run writes a path
        frame every few seconds, and building each pose in Python made a long ``--mcap`` run
        quadratic (minutes per thousand scans late in a 20,000-scan log). The bytes are
        those `rosbags` writes (little-endian CDR; ``tests/test_hostile_values.py`` checks).
        """
        pts = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(stamps, dtype=np.float64).reshape(-1)
        keep = np.all(np.isfinite(pts), axis=1)
        pts, t = pts[keep], t[keep]
        empty = bytes(
            self.ts.serialize_cdr(self.T[PATH](header=self._header(ns, "map"), poses=[]), PATH)
        )
        n = len(pts)
        if n == 0:
            return empty
        rec = np.zeros(n, dtype=_POSE_STAMPED)
        ok = np.isfinite(t) & (t >= 0)  # as stamp_ns: negative or non-finite stamps are 0
        sec = np.where(ok, np.floor(np.where(ok, t, 0.0)), 0.0)
        nsec = np.minimum(np.round((np.where(ok, t, 0.0) - sec) * 1e9), 10**9 - 1)
        rec["sec"], rec["nanosec"] = sec.astype(np.int32), nsec.astype(np.uint32)
        rec["frame_len"], rec["frame"] = 4, b"map"
        rec["x"], rec["y"] = pts[:, 0], pts[:, 1]
        q = yaw_to_quaternion(pts[:, 2])
        rec["qz"], rec["qw"] = q[:, 2], q[:, 3]
        body = rec.tobytes()
        # CDR aligns each float64 to 8 bytes from the data start (after the 4-byte
        # encapsulation header): only the first pose needs padding before its position
        start = len(empty) - 4  # the first pose's offset in the data (after the count)
        pad = (-(start + _POSE_HEADER)) % 8
        first = body[:_POSE_HEADER] + b"\0" * pad + body[_POSE_HEADER:_POSE_SIZE]
        return empty[:-4] + struct.pack("<I", n) + first + body[_POSE_SIZE:]

    def tf(self, ns: int, transforms: list[tuple[str, str, NDArray[np.float64]]]) -> bytes:
        """``tf2_msgs/TFMessage`` of ``(parent, child, pose)`` transforms."""
        T = self.T
        items = []
        for parent, child, pose in transforms:
            p = self._pose(pose)
            items.append(
                T["geometry_msgs/msg/TransformStamped"](
                    header=self._header(ns, parent),
                    child_frame_id=child,
                    transform=T["geometry_msgs/msg/Transform"](
                        translation=T["geometry_msgs/msg/Vector3"](
                            x=p.position.x, y=p.position.y, z=0.0
                        ),
                        rotation=p.orientation,
                    ),
                )
            )
        return bytes(self.ts.serialize_cdr(T[TF_MESSAGE](transforms=items), TF_MESSAGE))

    def png_image(self, image: NDArray[np.uint8], ns: int, frame: str) -> bytes:
        """``sensor_msgs/CompressedImage`` (PNG) of an RGB image."""
        msg = self.T[COMPRESSED_IMAGE](
            header=self._header(ns, frame),
            format="png",
            data=np.frombuffer(png_bytes(image), dtype=np.uint8),
        )
        return bytes(self.ts.serialize_cdr(msg, COMPRESSED_IMAGE))
