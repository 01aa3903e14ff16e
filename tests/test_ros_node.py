"""``scanguard node`` under a real ROS 1 master: the CCNY bag played, the map checked.

Each test starts its own ``roscore`` on a free port (``ROS_MASTER_URI``, ``ROS_HOME`` and the
log folder under the test's tmp folder) and kills every process group it started, also when
it fails. Skipped where ROS 1 (Debian's ``ros-core``, ``python3-rospy``...) is not installed,
or the shared CCNY bag is absent.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from scanguard.apps.ros1_node import import_rospy
from scanguard.errors import ConfigError
from scanguard.slam.grid import PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN, read_pgm

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT.parent / "shared" / "data" / "rosbag" / "ccny_laser_scan_matcher_demo.bag"
CCNY_SCANS = 360
SCANGUARD = Path(sys.executable).parent / "scanguard"
PLAY = ["rosbag", "play", "-q", "--wait-for-subscribers"]


def _ros_missing() -> str | None:
    try:
        import_rospy()
    except ConfigError as exc:
        return str(exc)
    for tool in ("roscore", "rosbag"):
        if shutil.which(tool) is None:
            return f"{tool} not on PATH (apt-get install ros-core python3-rosbag)"
    return None


MISSING = _ros_missing()
pytestmark = pytest.mark.skipif(MISSING is not None, reason=f"ROS 1 not installed: {MISSING}")
needs_bag = pytest.mark.skipif(not BAG.exists(), reason=f"shared CCNY bag absent: {BAG}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(
    what: str,
    check: Callable[[], object],
    timeout: float,
    alive: subprocess.Popen[bytes] | None = None,
) -> object:
    """Poll ``check`` until it is truthy; fail naming ``what`` after ``timeout`` s.

    With ``alive``: fail at once when that process has ended.
    """
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = check()
        if got:
            return got
        if alive is not None and alive.poll() is not None:
            pytest.fail(f"the process ended (status {alive.returncode}) before {what}")
        time.sleep(0.1)
    pytest.fail(f"timed out after {timeout:g} s waiting for {what}")


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Ros:
    """A roscore of one test and the processes started next to it (killed at the end)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        port = _free_port()
        self.env = {
            **os.environ,
            "ROS_MASTER_URI": f"http://127.0.0.1:{port}",
            "ROS_HOME": str(tmp / "ros_home"),
            "ROS_LOG_DIR": str(tmp / "ros_log"),
            "PYTHONUNBUFFERED": "1",
        }
        self.procs: list[subprocess.Popen[bytes]] = []
        self.core = self.spawn("roscore", ["roscore", "-p", str(port)])

    def spawn(self, name: str, cmd: list[str]) -> subprocess.Popen[bytes]:
        log = (self.tmp / f"{name}.log").open("wb")
        p = subprocess.Popen(
            cmd,
            env=self.env,
            cwd=ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: killed as a whole
            # Ctrl-C must reach it even when the tests run as a background job of a shell
            # without job control, which starts them with SIGINT ignored (inherited, and
            # Python then installs no KeyboardInterrupt handler): the node never stopped
            preexec_fn=_sigint_default,
        )
        self.procs.append(p)
        return p

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")

    def master_pid(self) -> int:
        """The rosmaster's pid (roslaunch starts it in a process group of its own)."""
        import xmlrpc.client

        return int(xmlrpc.client.ServerProxy(self.env["ROS_MASTER_URI"]).getPid("/test")[2])

    def close(self) -> None:
        master = None
        with contextlib.suppress(OSError):
            master = self.master_pid()
        for p in reversed(self.procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGINT)
                    p.wait(3)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    pass
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        if master is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(master, signal.SIGKILL)


@pytest.fixture
def ros(tmp_path: Path) -> Iterator[Ros]:
    from scanguard.apps.ros1_node import master_online

    r = Ros(tmp_path)
    try:
        wait_for("roscore", lambda: master_online(r.env["ROS_MASTER_URI"]), 30)
        yield r
    finally:
        r.close()


def _start_node(ros: Ros, out: Path, *params: str) -> subprocess.Popen[bytes]:
    node = ros.spawn("node", [str(SCANGUARD), "node", "-o", str(out), *params])
    wait_for("the node to subscribe", lambda: "listening on" in ros.log("node"), 90, node)
    return node


def _stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGINT) -> tuple[int, float]:
    """Send ``sig``; the exit status and the seconds until the process ended."""
    t0 = time.monotonic()
    proc.send_signal(sig)
    rc = proc.wait(30)
    return rc, time.monotonic() - t0


def _decisions(probe: Path) -> list[dict]:
    f = probe / "decisions.jsonl"
    if not f.exists():
        return []
    return [json.loads(line) for line in f.read_text().splitlines() if line.endswith("}")]


def _map_at(probe: Path, stamp: float) -> dict | None:
    for f in sorted(probe.glob("map_*.npz"), key=lambda p: int(p.stem.split("_")[1])):
        with np.load(f) as m:
            if abs(float(m["stamp"]) - stamp) < 1e-6:
                return {k: m[k] for k in m.files}
    return None


def _trinary(cells: np.ndarray) -> np.ndarray:
    """OccupancyGrid cells (row 0 = lowest y) as the PGM's values (top row = largest y)."""
    img = np.full(cells.shape, PGM_UNKNOWN, dtype=np.uint8)
    img[cells == 100] = PGM_OCCUPIED
    img[cells == 0] = PGM_FREE
    return img[::-1]


@needs_bag
def test_node_maps_the_ccny_bag_cell_for_cell_as_run_does(ros: Ros, tmp_path: Path) -> None:
    run_out = tmp_path / "run"
    ref = ros.spawn("run", [str(SCANGUARD), "run", str(BAG), "--no-compare", "-o", str(run_out)])
    probe = tmp_path / "probe"
    probe.mkdir()
    ros.spawn("probe", [sys.executable, "-m", "tests.ros.probe", str(probe)])
    # no-drop mode: the bag plays faster than the node on this machine, and a dropped scan
    # would change the map; every scan queued keeps the result the one of `scanguard run`
    node = _start_node(ros, tmp_path / "node", "_wait_for_scans:=true")
    wait_for(
        "the probe",
        lambda: (
            (probe / "connections").exists()
            and (probe / "connections").read_text() not in ("", "0")
        ),
        30,
    )
    subprocess.run(
        ["rosbag", "play", "-q", "--wait-for-subscribers", "-r", "4", str(BAG)],
        env=ros.env,
        cwd=ROOT,
        check=True,
        timeout=60,
        capture_output=True,
    )
    wait_for("every decision", lambda: len(_decisions(probe)) >= CCNY_SCANS, 120, node)
    decisions = _decisions(probe)
    assert [d["index"] for d in decisions] == list(range(CCNY_SCANS))
    assert all(d["dropped"] == 0 for d in decisions)
    # published once the node is idle for a second: the map of every scan
    last = decisions[-1]["stamp"]
    published = wait_for("the final map", lambda: _map_at(probe, last), 30, node)
    assert isinstance(published, dict)
    rc, seconds = _stop(node)
    assert rc == 0, ros.log("node")
    assert seconds < 2.0, f"the node took {seconds:.2f} s to stop after SIGINT"
    assert ref.wait(120) == 0, ros.log("run")
    expected = read_pgm(run_out / "map.pgm")
    # the same per-scan step on the same scans in the same order: the same map, every cell
    np.testing.assert_array_equal(_trinary(published["cells"]), expected)
    np.testing.assert_array_equal(read_pgm(tmp_path / "node" / "map.pgm"), expected)
    np.testing.assert_array_equal(
        np.loadtxt(tmp_path / "node" / "trajectory.tum"), np.loadtxt(run_out / "trajectory.tum")
    )
    metrics = json.loads((run_out / "metrics.json").read_text())
    rejected = sum(not d["accepted"] for d in decisions)
    assert rejected == metrics["counts"]["rejected"]
    # map -> odom: without odometry the robot's pose in the map (the last trajectory pose)
    x, y, _, _ = json.loads((probe / "tf.json").read_text())
    final = np.loadtxt(run_out / "trajectory.tum")[-1]
    assert (x, y) == pytest.approx((final[1], final[2]), abs=1e-6)
    stats = json.loads((tmp_path / "node" / "node.json").read_text())
    assert stats["processed"] == CCNY_SCANS and stats["dropped"] == 0


def _write_odometry_bag(path: Path, seed: int = 3, duration: float = 10.0) -> int:
    """A simulated lobby as a ROS 1 bag: ``/scan``, ``/tf`` (``odom -> base_link``), ``/odom``.

    The node reads odometry from ``/tf``, ``scanguard run`` from ``/odom``
    (``nav_msgs/Odometry``); both carry the same pose at each scan's stamp. Stamps start at
    1000 s (a float holds them to the nanosecond, so the node's tf lookup at a scan's stamp
    finds that very transform). Each transform is in the bag 10 ms before its scan, as a
    robot's odometry runs ahead of its laser. Returns the number of scans.
    """
    import_rospy()
    import rosbag
    import rospy
    from geometry_msgs.msg import TransformStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import LaserScan as ScanMsg
    from tf2_msgs.msg import TFMessage

    from scanguard.geometry import yaw_to_quaternion
    from scanguard.sim import simulate

    seq = simulate("lobby", seed=seed, duration=duration)
    assert seq.odometry is not None and not np.any(seq.laser_offset)  # the laser on base_link
    t0 = seq.scans[0].stamp - 1000.0
    with rosbag.Bag(str(path), "w") as bag:
        for scan, pose in zip(seq.scans, seq.odometry, strict=True):
            stamp = rospy.Time.from_sec(round(scan.stamp - t0, 6))
            q = np.asarray(yaw_to_quaternion(pose[2])).reshape(-1)
            tf = TransformStamped()
            tf.header.stamp, tf.header.frame_id, tf.child_frame_id = stamp, "odom", "base_link"
            tf.transform.translation.x, tf.transform.translation.y = pose[0], pose[1]
            tf.transform.rotation.z, tf.transform.rotation.w = q[2], q[3]
            odom = Odometry()
            odom.header, odom.child_frame_id = tf.header, "base_link"
            odom.pose.pose.position.x, odom.pose.pose.position.y = pose[0], pose[1]
            odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = q[2], q[3]
            msg = ScanMsg()
            msg.header.stamp, msg.header.frame_id = stamp, "base_link"
            msg.angle_min, msg.angle_increment = scan.angle_min, scan.angle_increment
            msg.angle_max = scan.angle_min + scan.angle_increment * (len(scan.ranges) - 1)
            msg.range_min, msg.range_max = scan.range_min, scan.range_max
            msg.ranges = scan.ranges.tolist()
            ahead = stamp - rospy.Duration.from_sec(0.01)
            bag.write("/tf", TFMessage(transforms=[tf]), ahead)
            bag.write("/odom", odom, ahead)
            bag.write("/scan", msg, stamp)
    return len(seq.scans)


def test_node_uses_odometry_from_tf_and_maps_as_run_does(ros: Ros, tmp_path: Path) -> None:
    bag = tmp_path / "lobby.bag"
    n = _write_odometry_bag(bag)
    run_out = tmp_path / "run"
    ref = ros.spawn("run", [str(SCANGUARD), "run", str(bag), "--no-compare", "-o", str(run_out)])
    probe = tmp_path / "probe"
    probe.mkdir()
    ros.spawn("probe", [sys.executable, "-m", "tests.ros.probe", str(probe)])
    node = _start_node(ros, tmp_path / "node", "_wait_for_scans:=true")
    wait_for("the probe", lambda: (probe / "connections").read_text() not in ("", "0"), 30)
    subprocess.run(
        # /odom is for `scanguard run` (nobody subscribes: --wait-for-subscribers would hang)
        [*PLAY, "-r", "2", str(bag), "--topics", "/scan", "/tf"],
        env=ros.env,
        cwd=ROOT,
        check=True,
        timeout=60,
        capture_output=True,
    )
    wait_for("every decision", lambda: len(_decisions(probe)) >= n, 120, node)
    decisions = _decisions(probe)
    assert [d["index"] for d in decisions] == list(range(n))
    # the fused motion drew on the wheels: the node took odometry from tf
    assert sum("wheels" in (d["motion_sources"] or ()) for d in decisions) > n // 2
    wait_for("the final map", lambda: _map_at(probe, decisions[-1]["stamp"]), 30, node)
    rc, seconds = _stop(node)
    assert rc == 0, ros.log("node")
    assert seconds < 2.0, f"the node took {seconds:.2f} s to stop after SIGINT"
    assert ref.wait(120) == 0, ros.log("run")
    stats = json.loads((tmp_path / "node" / "node.json").read_text())
    assert stats["odometry"] is True and stats["processed"] == n and stats["dropped"] == 0
    # The node's odometry is `scanguard run`'s: the same pose at the same stamp (tf at the
    # scan's stamp vs /odom interpolated there, both from one quaternion), so the same step
    # on the same inputs gives the same trajectory and map; the tolerance only absorbs the
    # last bits of two readings of each stamp and quaternion (rospy/tf2 vs the bag reader;
    # 1.5e-8 measured on 2026-12-02).
    np.testing.assert_allclose(
        np.loadtxt(tmp_path / "node" / "trajectory.tum"),
        np.loadtxt(run_out / "trajectory.tum"),
        rtol=0,
        atol=1e-6,
    )
    np.testing.assert_array_equal(
        read_pgm(tmp_path / "node" / "map.pgm"), read_pgm(run_out / "map.pgm")
    )
    metrics = json.loads((run_out / "metrics.json").read_text())
    assert sum(not d["accepted"] for d in decisions) == metrics["counts"]["rejected"]


def test_node_stops_within_two_seconds_when_the_master_goes(ros: Ros, tmp_path: Path) -> None:
    node = _start_node(ros, tmp_path / "node", "_use_odometry:=off")
    t0 = time.monotonic()
    os.kill(ros.master_pid(), signal.SIGKILL)  # the master, at once
    rc = node.wait(30)
    assert time.monotonic() - t0 < 2.0, ros.log("node")
    assert rc == 0, ros.log("node")
    assert "the ROS master went away" in ros.log("node")
    assert not (tmp_path / "node").exists()  # no scan, nothing to save
