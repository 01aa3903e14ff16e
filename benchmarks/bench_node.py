"""``scanguard node`` live: a bag played at real speed, dropped scans, latency, shutdown time.

Starts its own ``roscore`` on a free port, the node (``-o`` a temporary folder, default
settings plus any ``_param:=value`` given after the bag), plays the bag at real speed
(``rosbag play --wait-for-subscribers``), waits two seconds, sends SIGINT and prints the
node's counts and latency (``node.json``) and the seconds from SIGINT to its exit. Needs ROS 1
from Debian (see README, "Live on a robot").

    python benchmarks/bench_node.py [BAG] [_use_odometry:=off ...]

Default bag: ``../shared/data/rosbag/ccny_laser_scan_matcher_demo.bag``.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT.parent / "shared" / "data" / "rosbag" / "ccny_laser_scan_matcher_demo.bag"
SCANGUARD = Path(sys.executable).parent / "scanguard"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for(check: Callable[[], object], timeout: float) -> None:
    end = time.monotonic() + timeout
    while not check():
        if time.monotonic() > end:
            raise SystemExit("timed out")
        time.sleep(0.1)


def main(argv: list[str]) -> None:
    """Run the benchmark (see the module docstring)."""
    from scanguard.apps.ros1_node import master_online

    bag = Path(argv[0]) if argv and ":=" not in argv[0] else BAG
    params = [a for a in argv if ":=" in a]
    tmp = Path(tempfile.mkdtemp(prefix="bench_node_"))
    port = _port()
    env = {
        **os.environ,
        "ROS_MASTER_URI": f"http://127.0.0.1:{port}",
        "ROS_HOME": str(tmp / "ros_home"),
        "ROS_LOG_DIR": str(tmp / "ros_log"),
    }
    procs = []

    def spawn(name: str, cmd: list[str]) -> subprocess.Popen[bytes]:
        log = (tmp / f"{name}.log").open("wb")
        p = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        procs.append(p)
        return p

    try:
        spawn("roscore", ["roscore", "-p", str(port)])
        _wait_for(lambda: master_online(env["ROS_MASTER_URI"]), 30)
        node = spawn("node", [str(SCANGUARD), "node", "-o", str(tmp / "out"), *params])
        _wait_for(lambda: "listening on" in (tmp / "node.log").read_text(errors="replace"), 120)
        cmd = ["rosbag", "play", "-q", "--wait-for-subscribers", str(bag)]
        subprocess.run(cmd, env=env, check=True, capture_output=True, timeout=600)
        time.sleep(2.0)
        t0 = time.monotonic()
        node.send_signal(signal.SIGINT)
        rc = node.wait(30)
        shutdown = time.monotonic() - t0
        stats = json.loads((tmp / "out" / "node.json").read_text())
        print(json.dumps({**stats, "exit_status": rc, "sigint_to_exit_s": shutdown}, indent=1))
        print(f"logs: {tmp}")
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()


if __name__ == "__main__":
    main(sys.argv[1:])
