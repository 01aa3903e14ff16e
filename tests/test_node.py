"""`scanguard.apps.node` without ROS: parameters, the queue that drops, the worker's results."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from scanguard.apps.node import GuardNode, NodeOptions, NodeStats, node_settings
from scanguard.errors import ConfigError
from scanguard.slam.config import RunConfig
from tests.helpers import make_sequence, room_segments
from tests.test_run import AlignmentDetector


def test_slam_gmapping_parameters_map_onto_the_run_config():
    cfg, opts = node_settings(
        RunConfig(),
        {
            "particles": 12,
            "linearUpdate": 0.5,
            "maxUrange": 6.0,
            "delta": 0.1,
            "xmin": -20.0,
            "map_update_interval": 2,
            "wait_for_scans": "true",
            "use_odometry": False,
            "motion": "guarded-matches",
        },
    )
    g = cfg.gmapping
    assert (g.particles, g.linearUpdate, g.maxUrange, g.delta, g.xmin) == (12, 0.5, 6.0, 0.1, -20)
    assert cfg.motion == "guarded_matches" and cfg.compare is False
    assert opts.map_update_interval == 2.0 and opts.wait_for_scans is True
    assert opts.use_odometry == "off" and opts.queue_size == 1  # the default: never fall behind


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"partcles": 3}, "unknown node parameter"),
        ({"particles": 0}, "particles"),
        ({"queue_size": 0}, "queue_size"),
        ({"use_odometry": "maybe"}, "use_odometry"),
        ({"map_update_interval": "soon"}, "map_update_interval"),
    ],
)
def test_bad_parameters_are_one_line_errors(params, message):
    with pytest.raises(ConfigError, match=message):
        node_settings(RunConfig(), params)


class FakeTransport:
    """Records what the node publishes; no odometry, the laser on the robot's origin."""

    def __init__(self, gate: threading.Event | None = None) -> None:
        self.decisions: list[dict] = []
        self.maps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.gate = gate

    waits: list[tuple[str, float]]

    def odometry(self, stamp, timeout):
        self.waits = [*getattr(self, "waits", []), ("odometry", timeout)]
        return None

    def laser_offset(self, frame_id, stamp, timeout):
        self.waits = [*getattr(self, "waits", []), ("laser", timeout)]
        return np.zeros(3)

    def publish_decision(self, decision):
        json.dumps(decision, allow_nan=False)  # JSON-ready
        self.decisions.append(dict(decision))
        if self.gate is not None:
            self.gate.wait(5)  # hold the worker: the queue fills

    def publish_pose(self, stamp, map_to_odom, odometry):
        self.poses.append(np.asarray(map_to_odom))

    def publish_map(self, grid, stamp):
        self.maps.append(stamp)

    def publish_path(self, stamps, poses):
        assert len(stamps) == len(poses)

    def publish_status(self, status):
        pass


@pytest.fixture(scope="module")
def room():
    return make_sequence(room_segments(), np.tile([0.05, 0.0, 0.02], (7, 1)))


def _node(transport, **options) -> GuardNode:
    cfg = RunConfig(backend="frontend")
    return GuardNode(cfg, NodeOptions(**options), AlignmentDetector(), None, transport)


def _wait(cond, timeout=30.0):
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_the_worker_publishes_a_decision_per_scan_and_the_map_when_idle(room, tmp_path):
    t = FakeTransport()
    node = _node(t, wait_for_scans=True, map_update_interval=100.0)
    node.start()
    assert all(node.offer(s, "laser") for s in room.scans)
    _wait(lambda: len(t.maps) >= 2)  # the first scan's, then the idle one with every scan
    node.stop()
    assert [d["index"] for d in t.decisions] == list(range(len(room)))
    assert t.maps[-1] == room.scans[-1].stamp
    s = node.stats.summary()
    assert s["processed"] == len(room) and s["dropped"] == 0
    assert s["latency_ms"]["max"] >= s["latency_ms"]["p99"] >= s["latency_ms"]["median"] > 0
    files = node.save(tmp_path)
    assert {p.name for p in files} >= {"map.pgm", "map.yaml", "map.png", "trajectory.tum"}
    assert np.loadtxt(tmp_path / "trajectory.tum").shape == (len(room), 8)


def test_a_scan_that_arrives_while_the_queue_is_full_is_dropped_and_counted(room):
    gate = threading.Event()
    t = FakeTransport(gate)
    node = _node(t, queue_size=1)
    node.start()
    assert node.offer(room.scans[0], "laser")
    _wait(lambda: len(t.decisions) == 1)  # the worker holds scan 0
    assert node.offer(room.scans[1], "laser")  # waits in the queue
    assert not node.offer(room.scans[2], "laser")  # the queue is full: dropped, never blocks
    gate.set()
    _wait(lambda: len(t.decisions) == 2)
    node.stop()
    assert node.stats.dropped == 1 and node.stats.received == 3 and node.stats.processed == 2
    assert "1 dropped" in node.stats.line()


def test_stats_before_any_scan():
    assert NodeStats().summary()["latency_ms"]["p99"] is None


def test_a_gmapping_map_snapshot_is_unchanged_by_the_scans_fed_after_it(room):
    """The node's map thread builds from `map_builder` while the worker feeds the filter."""
    from scanguard.slam.gmapping import GMappingBackend, GMappingConfig

    backend = GMappingBackend(GMappingConfig(particles=4, temporalUpdate=0.0, seed=3))
    odometry = room.reference  # exact poses: every scan moves the filter
    for scan, odom in zip(room.scans[:4], odometry[:4], strict=True):
        backend.update(scan, odom)
    build = backend.map_builder()
    expected_traj, expected_grid = backend.trajectory(), backend.grid()
    for scan, odom in zip(room.scans[4:], odometry[4:], strict=True):
        backend.update(scan, odom)  # after the snapshot, before it is built
    traj, grid = build()
    assert traj.shape == (4, 3) and backend.trajectory().shape == (len(room), 3)
    np.testing.assert_array_equal(traj, expected_traj)
    np.testing.assert_array_equal(grid.logodds, expected_grid.logodds)
    np.testing.assert_array_equal(grid.origin, expected_grid.origin)
    now = backend.grid().logodds  # the later scans did change the map
    assert now.shape != grid.logodds.shape or not np.array_equal(now, grid.logodds)


@pytest.mark.parametrize(
    ("use", "age", "waits"),
    [
        ("auto", 10.0, [("odometry", 0.1), ("laser", 0.0)]),  # tf heard for 10 s: no stall
        ("auto", 0.0, [("odometry", 1.0), ("laser", 0.0)]),  # just made: the timeout's rest
        ("off", 10.0, [("laser", 0.1)]),
    ],
)
def test_the_first_scan_waits_for_tf_only_what_is_left_of_the_timeout(room, use, age, waits):
    t = FakeTransport()
    node = _node(t, use_odometry=use, odometry_timeout=1.0)
    node._made -= age  # the node (and the transport's tf listener) made ``age`` s ago
    for scan in room.scans[:3]:  # before the first is processed: queued, none dropped
        assert node.offer(scan, "laser")
    node.start()
    _wait(lambda: len(t.decisions) == 3)
    node.stop()
    assert [w for w, _ in t.waits] == [w for w, _ in waits]
    np.testing.assert_allclose([s for _, s in t.waits], [s for _, s in waits], atol=0.05)
    assert node.stats.dropped == 0 and node.odometry is False


def test_a_live_scan_is_checked_as_a_bag_scan_is() -> None:
    """The node builds scans with the bag reader's constructor: ranges that disagree with the
    angle fields are refused (the callback counts it), an empty stamp takes the arrival time."""
    from types import SimpleNamespace

    from scanguard.apps.ros1_node import scan_of
    from scanguard.errors import ScanError

    def msg(n: int, secs: int) -> SimpleNamespace:
        return SimpleNamespace(
            header=SimpleNamespace(stamp=SimpleNamespace(secs=secs, nsecs=500_000_000)),
            ranges=np.full(n, 2.0, dtype=np.float32), intensities=np.zeros(n, np.float32),
            angle_min=-1.0, angle_max=1.0, angle_increment=0.02, range_min=0.1, range_max=10.0,
        )  # fmt: skip

    scan = scan_of(msg(101, 7), now=99.0)
    assert scan.stamp == pytest.approx(7.5) and len(scan.ranges) == 101
    assert scan_of(msg(101, 0), now=99.0).stamp == pytest.approx(0.5)  # nsecs alone: kept
    with pytest.raises(ScanError):
        scan_of(msg(60, 7), now=99.0)


def test_two_scans_that_arrive_together_at_an_idle_node_are_both_taken(room):
    t = FakeTransport()
    node = _node(t, queue_size=1)
    node.start()
    assert node.offer(room.scans[0], "laser")
    _wait(lambda: node.stats.processed == 1 and not node._busy)
    # a burst: the first may still sit in the queue when the second comes; neither waits
    # behind a busy worker, so neither is dropped
    assert node.offer(room.scans[1], "laser") and node.offer(room.scans[2], "laser")
    _wait(lambda: node.stats.processed == 3)
    node.stop()
    assert node.stats.dropped == 0
