"""Issue 24, defect 7: ``max_scans`` stops the readers, and the scans read are a full read's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scanguard.io import read_sequence, write_sequence
from scanguard.scan import ScanSequence
from tests import bagkit
from tests.helpers import small_room_walk


def _same_prefix(full: ScanSequence, cut: ScanSequence, n: int) -> None:
    """``cut`` holds exactly the first ``n`` scans, odometry and reference of ``full``."""
    assert len(cut) == n < len(full)
    for a, b in zip(full.scans[:n], cut.scans, strict=True):
        assert a.stamp == b.stamp
        assert np.array_equal(a.ranges, b.ranges, equal_nan=True)
    for attr in ("odometry", "reference"):
        whole, part = getattr(full, attr), getattr(cut, attr)
        assert whole is not None and part is not None
        assert np.array_equal(whole[:n], part), attr
    assert np.array_equal(full.laser_offset, cut.laser_offset)


def _carmen_log(path: Path, n: int, *, garbage_after: int | None = None) -> Path:
    """A raw CARMEN log: ``n`` FLASER lines at 10 Hz, ODOM lines at 20 Hz between them."""
    lines = []
    for k in range(n):
        t = 100.0 + 0.1 * k
        for j in (0, 1):  # two ODOM lines per scan, the first one before it
            to = t - 0.05 + 0.05 * j
            odom = f"{0.01 * to:.6f} {0.002 * to:.6f} {0.3 * to:.6f}"
            lines.append(f"ODOM {odom} 0 0 0 {to:.6f} h {to}")
        ranges = " ".join(f"{2 + 0.01 * ((i + k) % 7):.3f}" for i in range(181))
        pose = f"{0.01 * t:.6f} {0.002 * t:.6f} {0.3 * t:.6f}"
        lines.append(f"FLASER 181 {ranges} {pose} {pose} {t:.6f} h {t:.6f}")
        if garbage_after is not None and k == garbage_after:
            lines.append("FLASER 181 1 2 3 garbage")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_carmen_max_scans_reads_a_full_reads_first_scans(tmp_path: Path) -> None:
    log = _carmen_log(tmp_path / "walk.log", 60)
    for odom in (None, "ODOM"):
        full = read_sequence(log, odom_topic=odom, reference_topic="laser")
        cut = read_sequence(log, odom_topic=odom, reference_topic="laser", max_scans=17)
        _same_prefix(full, cut, 17)
        assert cut.metadata["max_scans"] == 17


def test_carmen_max_scans_stops_parsing(tmp_path: Path) -> None:
    """A garbled line after the scans asked for is never parsed (a full read refuses it)."""
    log = _carmen_log(tmp_path / "bad.log", 60, garbage_after=30)
    with pytest.raises(Exception, match="line"):
        read_sequence(log)
    cut = read_sequence(log, max_scans=25, odom_topic="ODOM")
    assert len(cut) == 25 and cut.odometry is not None
    assert cut.scans[-1].stamp == pytest.approx(102.4)


def test_corrected_carmen_excerpt_with_max_scans() -> None:
    """The real Intel excerpt (its ODOM stamps step back): scans exact, ODOM to rounding."""
    p = Path(__file__).parent / "data" / "intel-corrected-excerpt.log.gz"
    full = read_sequence(p, odom_topic="ODOM")
    cut = read_sequence(p, odom_topic="ODOM", max_scans=30)
    assert [s.stamp for s in cut] == [s.stamp for s in full.scans[:30]]
    assert cut.reference is not None and full.reference is not None
    assert np.array_equal(cut.reference, full.reference[:30])
    assert cut.odometry is not None and full.odometry is not None
    # the full stream sorts later, earlier-stamped ODOM lines in: 2 pi rounding at most
    assert np.allclose(cut.odometry, full.odometry[:30], rtol=0, atol=1e-12)


def test_rosbag_max_scans_reads_a_full_reads_first_scans(tmp_path: Path) -> None:
    seq, _ = small_room_walk(0, 1, n=20)
    assert seq.reference is not None
    seq.odometry = seq.reference + 0.01
    bag = write_sequence(seq, tmp_path / "walk.mcap")
    full = read_sequence(bag)
    cut = read_sequence(bag, max_scans=7)
    _same_prefix(full, cut, 7)
    assert cut.metadata["max_scans"] == 7


def test_rosbag_max_scans_stops_reading(tmp_path: Path) -> None:
    """A malformed scan after the scans asked for is never decoded; poses are read on."""
    q = bagkit.yaw_quaternion(0.0)
    msgs: list[bagkit.Msg] = [
        ("/tf_static", "tf2_msgs/msg/TFMessage", 0.5, bagkit.tf_static((0.1, 0.0, 0.0), q))
    ]
    for k in range(10):
        t = 1.0 + k
        bad = k == 8  # a zero-beam scan: a full read refuses the bag
        msgs.append(
            ("/odom", "nav_msgs/msg/Odometry", t - 0.5, bagkit.odometry(t - 0.5, 0.1 * t, 0, q))
        )
        scan = bagkit.laser_scan(t, ranges=() if bad else (2.0,) * 5)
        msgs.append(("/scan", "sensor_msgs/msg/LaserScan", t, scan))
    msgs.append(("/odom", "nav_msgs/msg/Odometry", 20.0, bagkit.odometry(20.0, 2.0, 0, q)))
    bag = bagkit.write_ros2(tmp_path / "b", msgs)
    with pytest.raises(Exception, match="zero beams"):
        read_sequence(bag)
    cut = read_sequence(bag, max_scans=5)
    assert [s.stamp for s in cut] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert cut.odometry is not None
    # scan 5 (t = 5) lies between the odometry at 4.5 and at 5.5: both were read
    assert cut.odometry[4, 0] == pytest.approx(0.55)  # x = 0.5 at 4.5, 0.6 at 5.5
    assert np.allclose(cut.laser_offset, (0.1, 0.0, 0.0))
    assert cut.metadata["max_scans"] == 5
