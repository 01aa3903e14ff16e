"""Property tests: ROS 1 and ROS 2 bags built from generated LaserScan, Odometry and TF messages.

Whatever the messages hold (non-finite or negative ranges, inverted limits, non-unit or zero
quaternions, huge translations, equal or backward stamps), reading the bag gives either a
valid sequence (finite stamps, poses and laser offset) or one `ScanGuardError` line naming the
file: never another exception. Examples are derandomised (the same on every run).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scanguard.errors import ScanGuardError
from scanguard.io import read_sequence
from scanguard.scan import ScanSequence
from tests import bagkit

_FLOAT = st.one_of(
    st.floats(-1e3, 1e3),
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 0.0, -1.0, 1e300, -1e300]),
)
_RANGE = st.one_of(st.floats(0.0, 30.0), st.sampled_from([float("nan"), float("inf"), -1.0, 0.0]))
_STAMP = st.floats(0.0, 1e5)
_QUAT = st.one_of(
    st.tuples(_FLOAT, _FLOAT, _FLOAT, _FLOAT),
    st.floats(-3.0, 3.0).map(bagkit.yaw_quaternion),
    st.tuples(st.floats(-3.0, 3.0), st.floats(0.0, 3.0)).map(
        lambda a: bagkit.yaw_quaternion(a[0], scale=a[1])
    ),
)


@st.composite
def _messages(draw: st.DrawFn) -> tuple[list[bagkit.Msg], bool]:
    """Messages of one bag, and whether every value is well-formed (such a bag must read)."""
    sane = draw(st.booleans())
    if sane:  # increasing stamps, 20 good beams, unit quaternions, a sane laser offset
        n = draw(st.integers(2, 6))
        t0 = draw(st.floats(0.0, 1e5))
        stamps = [t0 + 0.1 * k for k in range(n)]
    else:
        n = draw(st.integers(0, 6))
        stamps = draw(st.lists(_STAMP, min_size=n, max_size=n))
    msgs: list[bagkit.Msg] = []
    for t in stamps:
        msgs.append(("/scan", "sensor_msgs/msg/LaserScan", t, _scan(draw, t, sane)))
        if draw(st.booleans()):
            if sane:
                pose = (draw(st.floats(-50, 50)), draw(st.floats(-50, 50)))
                q = bagkit.yaw_quaternion(draw(st.floats(-3.0, 3.0)))
            else:
                pose, q = (draw(_FLOAT), draw(_FLOAT)), draw(_QUAT)
            msgs.append(("/odom", "nav_msgs/msg/Odometry", t, bagkit.odometry(t, *pose, q)))
    if draw(st.booleans()):
        if sane:
            offset, q = (draw(st.floats(-1, 1)), 0.0, 0.0), bagkit.yaw_quaternion(0.0)
        else:
            offset, q = (draw(_FLOAT), draw(_FLOAT), 0.0), draw(_QUAT)
        msgs.insert(0, ("/tf_static", "tf2_msgs/msg/TFMessage", 0.0, bagkit.tf_static(offset, q)))
    return msgs, sane


def _scan(draw: st.DrawFn, t: float, sane: bool) -> bagkit.Builder:
    if sane:
        ranges = draw(st.lists(st.floats(0.5, 10.0), min_size=20, max_size=20))
        return bagkit.laser_scan(t, ranges=ranges, angle_min=-1.0, increment=0.1)
    beams = draw(st.integers(0, 12))
    return bagkit.laser_scan(
        t,
        ranges=draw(st.lists(_RANGE, min_size=beams, max_size=beams)),
        angle_min=draw(st.floats(-4.0, 4.0)),
        increment=draw(st.one_of(st.floats(-0.5, 0.5), st.just(0.1))),
        range_min=draw(st.one_of(st.floats(-1.0, 2.0), st.just(0.1))),
        range_max=draw(st.one_of(st.floats(-1.0, 40.0), st.just(20.0))),
    )


_PROPS = settings(max_examples=25, deadline=None, derandomize=True, database=None)


def _read_checked(path: Path, lenient: bool, sane: bool) -> None:
    try:
        seq = read_sequence(path, lenient=lenient)
    except ScanGuardError as exc:
        assert not sane, f"a well-formed bag was refused: {exc}"
        text = str(exc)
        assert "\n" not in text.strip() and len(text) < 2000
        assert path.name in text
        return
    assert isinstance(seq, ScanSequence) and len(seq) > 0
    if sane:
        assert len(seq) == len(seq.stamps) >= 2 and (seq.scans[0].points(np.float64).size > 0)
    assert np.isfinite(seq.stamps).all()
    assert np.isfinite(np.asarray(seq.laser_offset)).all()
    assert seq.odometry is None or np.isfinite(seq.odometry).all()
    for scan in seq.scans:
        pts = scan.points(np.float64)
        assert np.isfinite(pts).all()


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("ros-properties")


@_PROPS
@given(msgs=_messages(), lenient=st.booleans())
def test_generated_ros1_bags_read_or_fail_in_one_line(scratch: Path, msgs, lenient) -> None:
    path = scratch / "gen.bag"
    path.unlink(missing_ok=True)
    bagkit.write_ros1(path, msgs[0])
    _read_checked(path, lenient, msgs[1])


@_PROPS
@given(msgs=_messages(), lenient=st.booleans())
def test_generated_ros2_bags_read_or_fail_in_one_line(scratch: Path, msgs, lenient) -> None:
    import shutil

    folder = scratch / "gen2"
    shutil.rmtree(folder, ignore_errors=True)
    bagkit.write_ros2(folder, msgs[0])
    _read_checked(folder, lenient, msgs[1])
