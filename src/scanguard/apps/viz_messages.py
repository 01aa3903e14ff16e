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
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

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
        """``nav_msgs/Path`` of robot poses ``(N, 3)`` in the map frame."""
        T = self.T
        items = [
            T["geometry_msgs/msg/PoseStamped"](
                header=self._header(stamp_ns(float(t)), "map"), pose=self._pose(p)
            )
            for t, p in zip(stamps, poses, strict=True)
            if np.all(np.isfinite(p))
        ]
        msg = T[PATH](header=self._header(ns, "map"), poses=items)
        return bytes(self.ts.serialize_cdr(msg, PATH))

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
