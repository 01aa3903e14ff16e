"""Small ROS 1 / ROS 2 bags built message by message with `rosbags`, for the hostile tests.

``Msg`` values are ``(topic, msgtype, bag_stamp_s, builder)``; a builder takes the type store's
types and returns the message, so one description writes a ROS 1 bag (``std_msgs/Header``
with ``seq``) and a ROS 2 bag alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

Builder = Callable[[Any], Any]
Msg = tuple[str, str, float, Builder]

__all__ = [
    "laser_scan",
    "odometry",
    "string",
    "tf_static",
    "write_ros1",
    "write_ros2",
    "yaw_quaternion",
]


def yaw_quaternion(yaw: float, scale: float = 1.0) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a pure yaw, times ``scale`` (a non-unit quaternion when != 1)."""
    return (0.0, 0.0, scale * math.sin(yaw / 2), scale * math.cos(yaw / 2))


def _header(T: Any, stamp: float, frame: str) -> Any:
    sec = math.floor(stamp)
    time = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((stamp - sec) * 1e9))
    fields = T["std_msgs/msg/Header"].__dataclass_fields__
    if "seq" in fields:
        return T["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame)
    return T["std_msgs/msg/Header"](stamp=time, frame_id=frame)


def laser_scan(
    stamp: float,
    *,
    ranges: Sequence[float] = (2.0,) * 5,
    angle_min: float = -1.0,
    increment: float = 0.5,
    range_min: float = 0.1,
    range_max: float = 10.0,
    frame: str = "laser",
    angle_max: float | None = None,
) -> Builder:
    """A ``sensor_msgs/LaserScan`` builder (``angle_max``: the last beam's angle by default)."""

    def build(T: Any) -> Any:
        n = len(ranges)
        return T["sensor_msgs/msg/LaserScan"](
            header=_header(T, stamp, frame),
            angle_min=angle_min,
            angle_max=angle_min + increment * (n - 1) if angle_max is None else angle_max,
            angle_increment=increment,
            time_increment=0.0,
            scan_time=0.1,
            range_min=range_min,
            range_max=range_max,
            ranges=np.asarray(ranges, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32),
        )

    return build


def odometry(
    stamp: float, x: float, y: float, q: tuple[float, float, float, float], frame: str = "odom"
) -> Builder:
    """A ``nav_msgs/Odometry`` builder with orientation ``q = (x, y, z, w)``."""

    def build(T: Any) -> Any:
        vec = T["geometry_msgs/msg/Vector3"]
        return T["nav_msgs/msg/Odometry"](
            header=_header(T, stamp, frame),
            child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
                covariance=np.zeros(36),
            ),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)
                ),
                covariance=np.zeros(36),
            ),
        )

    return build


def tf_static(
    translation: tuple[float, float, float],
    q: tuple[float, float, float, float],
    child: str = "laser",
    parent: str = "base_link",
) -> Builder:
    """A ``tf2_msgs/TFMessage`` builder holding one transform ``parent -> child``."""

    def build(T: Any) -> Any:
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=_header(T, 0.0, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](
                    x=translation[0], y=translation[1], z=translation[2]
                ),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )
        return T["tf2_msgs/msg/TFMessage"](transforms=[tf])

    return build


def string(data: str) -> Builder:
    """A ``std_msgs/String`` builder."""
    return lambda T: T["std_msgs/msg/String"](data=data)


def write_ros1(path: Path, messages: Sequence[Msg]) -> Path:
    """A ROS 1 bag holding ``messages`` (one connection per ``(topic, msgtype)``)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    # the noetic store lacks tf2_msgs; its definition is the same in ROS 2
    tfm = "tf2_msgs/msg/TFMessage"
    ts.register({tfm: get_typestore(Stores.ROS2_HUMBLE).fielddefs[tfm]})
    with Writer(path) as w:
        conns: dict[tuple[str, str], Any] = {}
        for topic, msgtype, t, build in messages:
            key = (topic, msgtype)
            if key not in conns:
                conns[key] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[key], round(t * 1e9), ts.serialize_ros1(build(ts.types), msgtype))
    return path


def write_ros2(path: Path, messages: Sequence[Msg]) -> Path:
    """A ROS 2 bag folder (MCAP storage) holding ``messages``; returns the folder."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns: dict[tuple[str, str], Any] = {}
        for topic, msgtype, t, build in messages:
            key = (topic, msgtype)
            if key not in conns:
                conns[key] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[key], round(t * 1e9), ts.serialize_cdr(build(ts.types), msgtype))
    return path


def scans(n: int = 4, t0: float = 1.0, **kw: Any) -> list[Msg]:
    """``n`` identical scans on ``/scan``, 1 s apart (header and bag stamps alike)."""
    return [
        ("/scan", "sensor_msgs/msg/LaserScan", t0 + k, laser_scan(t0 + k, **kw)) for k in range(n)
    ]
