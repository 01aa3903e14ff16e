"""``scanguard node`` over ROS 1 (rospy): slam_gmapping's topics, parameters and frames.

The transport only: it reads the parameters, converts messages, looks transforms up and
publishes; `scanguard.apps.node.GuardNode` does the rest. rospy and the message packages come
from Debian (``apt-get install`` `DEBIAN_PACKAGES`), not from pip: their folder is appended to
``sys.path`` last (`import_rospy`), so the environment's own numpy and yaml stay in front.

Topics (relative names: remap them as any ROS node's): subscribes ``scan``
(``sensor_msgs/LaserScan``); publishes ``map`` (``nav_msgs/OccupancyGrid``, latched),
``map_metadata``, ``trajectory`` (``nav_msgs/Path``, latched), ``scanguard/decision``
(``std_msgs/String``, JSON per scan), ``~status`` (JSON, latched) and ``map -> odom`` on
``/tf`` (without odometry also ``odom -> base_link`` as identity, so the tree is whole).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.loop_setup import warm_up
from scanguard.apps.node import PARAMETERS, GuardNode, NodeOptions, node_settings
from scanguard.apps.viz_messages import grid_cells
from scanguard.errors import ConfigError, ScanGuardError
from scanguard.geometry import quaternion_to_yaw, yaw_to_quaternion
from scanguard.io.rosbag import laser_scan_of
from scanguard.scan import LaserScan

logger = logging.getLogger(__name__)

#: The Debian packages of ROS 1 the node needs (Debian 12 ships ROS 1 Noetic's core).
DEBIAN_PACKAGES = (
    "ros-core python3-rospy python3-rosbag python3-sensor-msgs python3-nav-msgs "
    "python3-geometry-msgs python3-tf2-msgs python3-tf2-ros"
)
#: Where Debian installs them.
DIST_PACKAGES = "/usr/lib/python3/dist-packages"
#: Seconds between checks that the master is still there.
MASTER_CHECK_SECONDS = 0.5


def import_rospy() -> Any:
    """rospy, from the environment or Debian's folder (appended last to ``sys.path``).

    Raises:
        ConfigError: ROS 1 is not installed.
    """
    try:
        import rospy
    except ImportError:
        if DIST_PACKAGES not in sys.path:
            sys.path.append(DIST_PACKAGES)
        try:
            import rospy
        except ImportError:
            raise ConfigError(
                f"ROS 1 (rospy) is not installed: apt-get install {DEBIAN_PACKAGES}"
            ) from None
    return rospy


def master_online(uri: str, timeout: float = 0.5) -> bool:
    """Whether something listens at the ROS master's address (a TCP connect, no XML-RPC)."""
    u = urlparse(uri)
    try:
        with socket.create_connection((u.hostname or "localhost", u.port or 11311), timeout):
            return True
    except OSError:
        return False


def _pose_of(transform: Any) -> NDArray[np.float64]:
    t, q = transform.translation, transform.rotation
    yaw = float(np.asarray(quaternion_to_yaw([q.x, q.y, q.z, q.w])).reshape(-1)[0])
    return np.array([t.x, t.y, yaw], dtype=np.float64)


class Ros1Transport:
    """`scanguard.apps.node.Transport` over rospy (see the module docstring)."""

    def __init__(self, rospy: Any, options: NodeOptions) -> None:
        import tf2_ros
        from nav_msgs.msg import MapMetaData, OccupancyGrid, Path
        from std_msgs.msg import String

        self.rospy, self.options = rospy, options
        self.buffer = tf2_ros.Buffer(rospy.Duration(30.0))
        self.listener = tf2_ros.TransformListener(self.buffer)
        self.broadcaster = tf2_ros.TransformBroadcaster()
        self._tf_errors = (
            tf2_ros.LookupException,
            tf2_ros.ConnectivityException,
            tf2_ros.ExtrapolationException,
            tf2_ros.TransformException,
        )
        self.pub_map = rospy.Publisher("map", OccupancyGrid, latch=True, queue_size=1)
        self.pub_meta = rospy.Publisher("map_metadata", MapMetaData, latch=True, queue_size=1)
        self.pub_path = rospy.Publisher("trajectory", Path, latch=True, queue_size=1)
        self.pub_decision = rospy.Publisher("scanguard/decision", String, queue_size=1000)
        self.pub_status = rospy.Publisher("~status", String, latch=True, queue_size=1)
        self._latest: tuple[NDArray[np.float64], bool] | None = None
        self._closed = threading.Event()
        self._tf_thread: threading.Thread | None = None
        if options.transform_publish_period > 0:
            self._tf_thread = threading.Thread(target=self._publish_tf, daemon=True)
            self._tf_thread.start()

    def close(self) -> None:
        """Stop republishing the transform."""
        self._closed.set()
        if self._tf_thread is not None:
            self._tf_thread.join(1.0)

    # --- Transport ---------------------------------------------------------------------

    def _lookup(
        self, parent: str, child: str, stamp: float | None, timeout: float
    ) -> NDArray[np.float64] | None:
        rospy = self.rospy
        at = rospy.Time(0) if stamp is None else rospy.Time.from_sec(stamp)
        try:
            msg = self.buffer.lookup_transform(parent, child, at, rospy.Duration(timeout))
        except self._tf_errors:
            return None
        return _pose_of(msg.transform)

    def odometry(self, stamp: float, timeout: float) -> NDArray[np.float64] | None:
        """``odom_frame -> base_frame`` at the scan's stamp."""
        return self._lookup(self.options.odom_frame, self.options.base_frame, stamp, timeout)

    def laser_offset(
        self, frame_id: str, stamp: float, timeout: float
    ) -> NDArray[np.float64] | None:
        """``base_frame -> frame_id`` (latest; the laser is fixed on the robot)."""
        if frame_id.strip("/") == self.options.base_frame.strip("/"):
            return np.zeros(3)
        return self._lookup(self.options.base_frame, frame_id.strip("/"), None, timeout)

    def publish_decision(self, decision: Mapping[str, Any]) -> None:
        """JSON on ``scanguard/decision``."""
        self.pub_decision.publish(json.dumps(dict(decision), allow_nan=False))

    def publish_status(self, status: Mapping[str, Any]) -> None:
        """JSON on ``~status`` (latched)."""
        self.pub_status.publish(json.dumps(dict(status), allow_nan=False))

    def publish_pose(self, stamp: float, map_to_odom: NDArray[np.float64], odometry: bool) -> None:
        """Keep the transform for the publisher thread (or publish it now at the scan stamp)."""
        self._latest = (np.asarray(map_to_odom, dtype=np.float64), odometry)
        if self._tf_thread is None:
            self._send(self.rospy.Time.from_sec(stamp))

    def _publish_tf(self) -> None:
        period = self.options.transform_publish_period
        while not self._closed.wait(period):
            if self._latest is not None and not self.rospy.is_shutdown():
                # as slam_gmapping: stamped ahead by one period, so lookups never extrapolate
                self._send(self.rospy.Time.now() + self.rospy.Duration(period))

    def _send(self, stamp: Any) -> None:
        if self._latest is None:
            return
        pose, odometry = self._latest
        o = self.options
        out = [self._transform(stamp, o.map_frame, o.odom_frame, pose)]
        if not odometry:
            out.append(self._transform(stamp, o.odom_frame, o.base_frame, np.zeros(3)))
        self.broadcaster.sendTransform(out)

    @staticmethod
    def _transform(stamp: Any, parent: str, child: str, pose: NDArray[np.float64]) -> Any:
        from geometry_msgs.msg import TransformStamped

        t = TransformStamped()
        t.header.stamp, t.header.frame_id, t.child_frame_id = stamp, parent, child
        t.transform.translation.x, t.transform.translation.y = float(pose[0]), float(pose[1])
        q = np.asarray(yaw_to_quaternion(pose[2])).reshape(-1)
        t.transform.rotation.z, t.transform.rotation.w = float(q[2]), float(q[3])
        return t

    def publish_map(self, grid: Any, stamp: float) -> None:
        """``map`` and ``map_metadata`` (the cells of the PGM ``scanguard run`` writes)."""
        from nav_msgs.msg import MapMetaData, OccupancyGrid

        cells = grid_cells(grid)
        info = MapMetaData()
        info.map_load_time = self.rospy.Time.from_sec(stamp)
        info.resolution = float(grid.resolution)
        info.height, info.width = int(cells.shape[0]), int(cells.shape[1])
        info.origin.position.x, info.origin.position.y = (float(v) for v in grid.origin)
        info.origin.orientation.w = 1.0
        msg = OccupancyGrid()
        msg.header.stamp, msg.header.frame_id = info.map_load_time, self.options.map_frame
        msg.info = info
        # a list: genpy packs int8[] from a sequence (numpy_msg's path needs numpy < 2)
        msg.data = cells.reshape(-1).tolist()
        self.pub_map.publish(msg)
        self.pub_meta.publish(info)

    def publish_path(self, stamps: NDArray[np.float64], poses: NDArray[np.float64]) -> None:
        """``trajectory``: every pose so far."""
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path

        msg = Path()
        msg.header.frame_id = self.options.map_frame
        if len(stamps):
            msg.header.stamp = self.rospy.Time.from_sec(float(stamps[-1]))
        q = np.asarray(yaw_to_quaternion(poses[:, 2])).reshape(-1, 4)
        for t, p, qq in zip(stamps, poses, q, strict=True):
            ps = PoseStamped()
            ps.header.stamp, ps.header.frame_id = self.rospy.Time.from_sec(float(t)), "map"
            ps.pose.position.x, ps.pose.position.y = float(p[0]), float(p[1])
            ps.pose.orientation.z, ps.pose.orientation.w = float(qq[2]), float(qq[3])
            msg.poses.append(ps)
        self.pub_path.publish(msg)


def scan_of(msg: Any, now: float) -> LaserScan:
    """A `LaserScan` of a ``sensor_msgs/LaserScan`` (numpy_msg), checked as the bag reader does.

    Raises:
        ScanError: Its ranges disagree with its angle fields (or the scan's own checks fail).
    """
    stamp = float(msg.header.stamp.secs) + float(msg.header.stamp.nsecs) * 1e-9
    # some drivers leave header stamps empty
    return laser_scan_of(msg, stamp if stamp != 0.0 else now)


def read_parameters(rospy: Any) -> dict[str, Any]:
    """The node's private parameters that are set (``_name:=value`` or a launch file)."""
    names = (*PARAMETERS, "config", "save_on_exit")
    return {n: rospy.get_param(f"~{n}") for n in names if rospy.has_param(f"~{n}")}


def _init_node(rospy: Any, argv: list[str]) -> None:
    """``rospy.init_node``, keeping the command's log handlers (rospy replaces the root's)."""
    root, ours = logging.getLogger(), logging.getLogger("scanguard")
    handlers, level = list(root.handlers), ours.level
    rospy.init_node("scanguard", argv=["scanguard", *argv], disable_signals=True)
    for h in handlers:
        if h not in root.handlers:
            root.addHandler(h)
    for name, lg in logging.root.manager.loggerDict.items():
        if name.startswith("scanguard") and isinstance(lg, logging.Logger):
            lg.disabled = False  # rospy's logging config disables the loggers made before it
    ours.setLevel(level)


def _wait(rospy: Any, node: GuardNode, uri: str) -> str:
    """Block until Ctrl-C, rospy's shutdown, the master going away or a worker error."""
    next_check = time.monotonic()
    try:
        while not rospy.is_shutdown() and node.running:
            time.sleep(0.05)
            if time.monotonic() >= next_check:
                next_check = time.monotonic() + MASTER_CHECK_SECONDS
                if not master_online(uri):
                    return "the ROS master went away"
    except KeyboardInterrupt:
        return "interrupted"
    return "worker stopped" if node.error is not None else "ROS shut down"


def serve(
    *,
    config: str | None,
    detector: Any,
    baseline: Any,
    argv: list[str],
    save: Any = None,
) -> dict[str, Any]:
    """Run the node until Ctrl-C or the master goes; its final stats.

    Args:
        config: A `RunConfig` YAML file (else the ``~config`` parameter, else the defaults).
        detector: The CNN fault detector.
        baseline: The classical detector (for a guard policy that uses one), or None.
        argv: ROS arguments: remappings (``scan:=/front/scan``), ``_param:=value``.
        save: A `scanguard.fsutil.ResultDir` for the final map and trajectory, or None.

    Raises:
        ConfigError: No ROS 1, no master, a bad parameter.
    """
    from scanguard.slam.config import RunConfig

    rospy = import_rospy()
    from rospy.numpy_msg import numpy_msg
    from sensor_msgs.msg import LaserScan as ScanMsg

    uri = os.environ.get("ROS_MASTER_URI", "http://localhost:11311")
    if not master_online(uri):
        raise ConfigError(f"no ROS master at {uri} (ROS_MASTER_URI): start roscore first")
    _init_node(rospy, argv)
    params = read_parameters(rospy)
    path = config or params.pop("config", None)
    params.pop("config", None)
    keep = bool(params.pop("save_on_exit", save is not None))
    base = RunConfig.from_yaml(path) if path else RunConfig()
    cfg, options = node_settings(base, params)
    # tf first: the warm-up's seconds count towards `use_odometry: auto`'s wait
    transport = Ros1Transport(rospy, options)
    node = GuardNode(cfg, options, detector, baseline, transport)
    logger.info("warming up (kernels and model): %.1f s", warm_up(cfg, detector, baseline))
    node.start()

    def callback(msg: Any) -> None:
        try:
            node.offer(scan_of(msg, time.time()), str(msg.header.frame_id))
        except ScanGuardError as exc:  # a malformed message: counted, never stops the node
            node.stats.failed += 1
            logger.warning("scan message refused: %s", exc)

    size = None if options.wait_for_scans else 10
    sub = rospy.Subscriber("scan", numpy_msg(ScanMsg), callback, queue_size=size)
    logger.info("listening on %s", sub.resolved_name)
    why = _wait(rospy, node, uri)
    t0 = time.monotonic()
    sub.unregister()
    node.stop()
    logger.info("stopping (%s): %s", why, node.stats.line())
    summary = {**node.stats.summary(), "stopped": why}
    try:
        if node.error is not None:
            raise node.error
        if keep and save is not None and node.loop is not None:
            with save as tmp:
                summary["files"] = [str(save.final(p)) for p in node.save(Path(tmp))]
    finally:
        transport.close()
        rospy.signal_shutdown(why)
        summary["shutdown_s"] = time.monotonic() - t0
        logger.info("stopped in %.2f s", summary["shutdown_s"])
    return summary
