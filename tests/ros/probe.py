"""A ROS 1 listener for tests/test_ros_node.py: records what ``scanguard node`` publishes.

Run as ``python -m tests.ros.probe OUT_DIR`` (ROS_MASTER_URI set). Writes into OUT_DIR:
``decisions.jsonl`` (one line per decision), ``map_<n>.npz`` (every map: cells, stamp,
origin, resolution), ``tf.json`` (the last ``map -> odom``), ``ready`` once subscribed.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from scanguard.apps.ros1_node import import_rospy


def main(out: Path) -> None:
    rospy = import_rospy()
    from nav_msgs.msg import OccupancyGrid
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage

    rospy.init_node("probe", anonymous=True, disable_signals=True)
    decisions = (out / "decisions.jsonl").open("a", buffering=1)
    maps = [0]

    def on_decision(msg: String) -> None:
        decisions.write(msg.data + "\n")

    def on_map(msg: OccupancyGrid) -> None:
        cells = (
            np.frombuffer(bytes(bytearray(msg.data)), dtype=np.int8)
            if isinstance(msg.data, (bytes, bytearray))
            else np.asarray(msg.data, dtype=np.int8)
        )
        info = msg.info
        tmp = out / f".map_{maps[0]}.npz"
        np.savez(
            tmp,
            cells=cells.reshape(info.height, info.width),
            stamp=msg.header.stamp.to_sec(),
            origin=[info.origin.position.x, info.origin.position.y],
            resolution=info.resolution,
        )
        os.replace(tmp, out / f"map_{maps[0]}.npz")
        maps[0] += 1

    def on_tf(msg: TFMessage) -> None:
        for t in msg.transforms:
            if t.header.frame_id == "map" and t.child_frame_id == "odom":
                tr, q = t.transform.translation, t.transform.rotation
                (out / ".tf.json").write_text(json.dumps([tr.x, tr.y, q.z, q.w]))
                os.replace(out / ".tf.json", out / "tf.json")

    subs = [
        rospy.Subscriber("scanguard/decision", String, on_decision, queue_size=1000),
        rospy.Subscriber("map", OccupancyGrid, on_map, queue_size=10),
        rospy.Subscriber("tf", TFMessage, on_tf, queue_size=100),
    ]
    (out / "ready").write_text("subscribed\n")
    try:
        while not rospy.is_shutdown():
            time.sleep(0.05)
            n = subs[0].get_num_connections()
            (out / "connections").write_text(str(n))
    except KeyboardInterrupt:
        pass
    decisions.close()
    rospy.signal_shutdown("probe done")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
