"""Hostile-input audit 2 (issue 24), the readers' numeric domains: defects 9, 10, 12, 16-18.

Bags are built message by message with `rosbags` (`tests.bagkit`); each case has a known
answer: the value read, the warning given or the one-line error naming the file.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from scanguard.errors import FormatError, InputError
from scanguard.io import read_sequence, read_tum, summarize
from scanguard.io.relations import read_relations
from tests import bagkit
from tests.bagkit import laser_scan, odometry, string, tf_static, write_ros1, write_ros2
from tests.test_hostile_io import flaser, one_line, warnings_of, write

ODOM = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"


def _odom(q: tuple[float, float, float, float], n: int = 4) -> list[bagkit.Msg]:
    return [(("/odom", ODOM, 1.0 + k, odometry(1.0 + k, 0.1 * k, 0.0, q))) for k in range(n)]


def _tf(translation=(0.1, 0.0, 0.0), q=None) -> list[bagkit.Msg]:
    q = bagkit.yaw_quaternion(0.5) if q is None else q
    return [("/tf_static", TF, 0.5, tf_static(translation, q))]


# --- defect 9: non-unit quaternions -------------------------------------------------------------


@pytest.mark.parametrize("writer", [write_ros1, write_ros2])
def test_scaled_odometry_quaternion_is_normalised_with_a_warning(tmp_path, caplog, writer):
    bag = writer(
        tmp_path / ("q3.bag" if writer is write_ros1 else "q3"),
        bagkit.scans(4) + _odom(bagkit.yaw_quaternion(0.1, 3.0)),
    )
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        seq = read_sequence(bag)
    # the audit read yaw 0.1 as 0.755 rad
    np.testing.assert_allclose(seq.odometry[:, 2], 0.1, atol=1e-9)
    assert any("4 orientation quaternion(s) off unit norm" in m for m in warnings_of(caplog))


def test_zero_odometry_quaternion_is_refused_or_skipped(tmp_path):
    msgs = bagkit.scans(4) + _odom(bagkit.yaw_quaternion(0.2))[:3]
    msgs.append(("/odom", ODOM, 4.0, odometry(4.0, 0.3, 0.0, (0.0, 0.0, 0.0, 0.0))))
    bag = write_ros1(tmp_path / "q0.bag", msgs)
    with pytest.raises(FormatError) as err:
        read_sequence(bag)
    text = one_line(err.value)
    assert "q0.bag, topic /odom: message 3: zero or non-finite orientation quaternion" in text
    seq = read_sequence(bag, lenient=True)
    assert seq.metadata["skipped_lines"] == 1
    np.testing.assert_allclose(seq.odometry[:3, 2], 0.2, atol=1e-9)


def test_tf_static_quaternion_scaled_by_3_is_normalised(tmp_path, caplog):
    bag = write_ros1(tmp_path / "tf.bag", bagkit.scans(3) + _tf(q=bagkit.yaw_quaternion(0.5, 3.0)))
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        seq = read_sequence(bag)
    # the audit read a laser yaw of 0.5 rad as 1.594 rad
    np.testing.assert_allclose(seq.laser_offset, [0.1, 0.0, 0.5], atol=1e-9)
    assert any("/tf_static: rotation" in m and "norm 3" in m for m in warnings_of(caplog))


@pytest.mark.parametrize(
    ("translation", "q", "problem"),
    [
        ((1e300, 0.0, 0.0), bagkit.yaw_quaternion(0.5), "translation (1e+300, 0)"),
        ((0.1, math.nan, 0.0), bagkit.yaw_quaternion(0.5), "translation (0.1, nan)"),
        ((0.1, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), "zero or non-finite quaternion"),
    ],
)
def test_absurd_tf_static_is_one_line(tmp_path, caplog, translation, q, problem):
    bag = write_ros1(tmp_path / "tf.bag", bagkit.scans(3) + _tf(translation, q))
    with pytest.raises(FormatError) as err:
        read_sequence(bag)
    text = one_line(err.value)
    assert text.startswith(f"{bag}, topic /tf_static: transform to laser:") and problem in text
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        seq = read_sequence(bag, lenient=True)
    assert seq.laser_offset.tolist() == [0.0, 0.0, 0.0]
    assert any("ignored transform to laser" in m for m in warnings_of(caplog))


def test_tum_non_unit_quaternion_warns_and_bom_is_accepted(tmp_path, caplog):
    qz, qw = 3 * math.sin(0.15), 3 * math.cos(0.15)
    path = tmp_path / "t.tum"
    path.write_bytes(b"\xef\xbb\xbf" + f"1.0 1 2 0 0 0 {qz} {qw}\r2.0 2 2 0 0 0 0 1\r".encode())
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        stamps, poses = read_tum(path)
    assert stamps.tolist() == [1.0, 2.0]
    np.testing.assert_allclose(poses[:, 2], [0.3, 0.0], atol=1e-12)
    assert any("1 quaternion(s) off unit norm" in m for m in warnings_of(caplog))


# --- defect 10: header stamps that are all equal ------------------------------------------------


def _equal_stamps_bag(tmp_path: Path, odom: bool = True) -> Path:
    msgs = [("/scan", "sensor_msgs/msg/LaserScan", 1.0 + k, laser_scan(5.0)) for k in range(30)]
    if odom:
        msgs += [
            ("/odom", ODOM, 1.0 + k, odometry(5.0, 0.1 * k, 0, (0, 0, 0, 1))) for k in range(30)
        ]
    return write_ros1(tmp_path / "eq.bag", msgs)


def test_equal_header_stamps_are_unreliable_and_never_aligned(tmp_path, caplog):
    bag = _equal_stamps_bag(tmp_path)
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        seq = read_sequence(bag)
    note = "only 1 distinct header stamp(s) on /scan for 30 scans"
    assert seq.metadata["stamps_unreliable"] == note
    s = summarize(seq)
    assert s["rate_hz"] is None and s["duration_s"] is None and s["stamps_note"] == note
    # the odometry picked by default cannot be aligned: dropped with a warning, not smeared
    assert seq.odometry is None
    assert any("cannot align /odom" in m for m in warnings_of(caplog))
    with pytest.raises(InputError, match=r"eq\.bag, topic /odom: cannot align /odom"):
        read_sequence(bag, odom_topic="/odom")
    # an external reference would give every scan one pose (and every pair the label normal)
    tum = tmp_path / "good.tum"
    tum.write_text("".join(f"{5.0 + k} {0.1 * k} 0 0 0 0 0 1\n" for k in range(30)))
    with pytest.raises(InputError) as err:
        read_sequence(bag, reference=tum)
    assert "good.tum: cannot align TUM poses with the scans of eq" in one_line(err.value)


# --- defect 12: hostile bag contents --------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        ("[1]", "expected a JSON object, found list"),
        ("null", "expected a JSON object, found NoneType"),
        ('{"sensor":"x"}', "'sensor' must be an object, found str"),
        ('{"metadata":[1,2]}', "'metadata' must be an object, found list"),
        ("[" * 100_000, "info message nested too deeply"),
        ('{"laser_offset":[1e300,0,0]}', "laser_offset [1e+300, 0, 0] beyond"),
        ('{"laser_offset":"abc"}', "'laser_offset' must be a list"),
        ('{"sensor":{"rate_hz":-1}}', "rate_hz must be a positive number, found -1"),
        ("{bad", "info message is not JSON"),
    ],
)
def test_malformed_info_message_is_one_line(tmp_path, caplog, data, problem):
    bag = write_ros2(
        tmp_path / "info",
        [*bagkit.scans(3), ("/scanguard/info", "std_msgs/msg/String", 0.5, string(data))],
    )
    with pytest.raises(FormatError) as err:
        read_sequence(bag)
    text = one_line(err.value)
    assert text.startswith(f"{bag}, topic /scanguard/info:") and problem in text
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        seq = read_sequence(bag, lenient=True)  # read as any bag, without our info
    assert len(seq) == 3 and seq.name == "info"
    assert any("/scanguard/info: ignored" in m for m in warnings_of(caplog))


def test_topic_with_two_message_types_is_one_line(tmp_path):
    msgs = [*bagkit.scans(3), ("/scan", "std_msgs/msg/String", 0.5, string("x"))]
    bag = write_ros1(tmp_path / "two.bag", msgs)
    with pytest.raises(FormatError) as err:
        read_sequence(bag)
    assert one_line(err.value) == (
        f"{bag}, topic /scan: topic recorded with several message types "
        "(sensor_msgs/msg/LaserScan, std_msgs/msg/String)"
    )


@pytest.mark.parametrize("keep", [0, 4, 8, 200, -1])
def test_cut_mcap_is_one_line(tmp_path, keep):
    folder = write_ros2(tmp_path / "whole", bagkit.scans(3))
    data = next(folder.glob("*.mcap")).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: keep if keep >= 0 else len(data) - 1])
    with pytest.raises(FormatError) as err:
        read_sequence(cut)
    text = one_line(err.value)
    assert text.startswith(f"{cut}: ")
    assert ("not an MCAP file" if 0 <= keep < 8 else "truncated MCAP file") in text


def test_metadata_yaml_nested_50k_deep_is_one_line(tmp_path):
    folder = write_ros2(tmp_path / "deep", bagkit.scans(3))
    (folder / "metadata.yaml").write_text("[" * 50_000)
    with pytest.raises(FormatError) as err:
        read_sequence(folder)
    # the bounded loader refuses it first, naming the file inside the bag folder
    assert one_line(err.value).startswith(f"{folder}/metadata.yaml: not valid YAML")


# --- defect 17: impossible scans ------------------------------------------------------------------


def test_range_min_above_range_max_names_the_cause(tmp_path):
    bag = write_ros1(tmp_path / "rr.bag", bagkit.scans(3, range_min=20.0, range_max=10.0))
    with pytest.raises(FormatError) as err:
        read_sequence(bag)
    text = one_line(err.value)
    assert "rr.bag, topic /scan: message 0:" in text
    assert "range limits 20 .. 10 m: no beam can be valid" in text


def test_negative_range_min_is_clamped_and_never_makes_points(tmp_path, caplog):
    ranges = [0.0, -1.0, 2.0, 0.05, 3.0]
    bag = write_ros1(tmp_path / "neg.bag", bagkit.scans(3, range_min=-5.0, ranges=ranges))
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        seq = read_sequence(bag)
    s0 = seq[0]
    assert s0.range_min == 0.0
    assert s0.valid.tolist() == [False, False, True, True, True]
    assert len(s0.points()) == 3
    assert any("3 scan(s) with a negative range_min; read as 0" in m for m in warnings_of(caplog))


def _robotlaser(max_range: float, fov: float, res: float = 0.01, n: int = 101) -> str:
    ranges = " ".join(["1.0"] * n)
    return "".join(
        f"ROBOTLASER1 0 -0.5 {fov} {res} {max_range} 0.01 0 {n} {ranges} 0 "
        f"0 0 0 {k} 0 0 0 0 0 0 0 {k}.0 h {k}.0\n"
        for k in range(3)
    )


@pytest.mark.parametrize("max_range", [0.0, -3.0])
def test_robotlaser_max_range_not_positive_names_the_cause(tmp_path, max_range):
    path = write(tmp_path / "mr.clf", _robotlaser(max_range, fov=1.0))
    with pytest.raises(FormatError) as err:
        read_sequence(path)
    text = one_line(err.value)
    assert "mr.clf, line 1: ROBOTLASER1:" in text and "no beam can be valid" in text


def test_robotlaser_field_of_view_mismatch_warns(tmp_path, caplog):
    good = write(tmp_path / "good.clf", _robotlaser(50.0, fov=1.0))  # 100 x 0.01
    bad = write(tmp_path / "bad.clf", _robotlaser(50.0, fov=3.0))
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        read_sequence(good)
        assert not any("field of view" in m for m in warnings_of(caplog))
        seq = read_sequence(bad)
    assert seq.sensor.fov_deg == pytest.approx(np.degrees(1.0))  # resolution wins
    assert any(
        "3 ROBOTLASER1 line(s) state a field of view that is not beams x resolution" in m
        for m in warnings_of(caplog)
    )


# --- defect 18: text encodings --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("prefix", "newline"), [(b"\xef\xbb\xbf", "\n"), (b"", "\r"), (b"\xef\xbb\xbf", "\r\n")]
)
def test_carmen_bom_and_any_line_ending_keep_every_scan(tmp_path, prefix, newline):
    text = "".join(flaser(t=float(k)) for k in range(1, 4)).replace("\n", newline)
    path = write(tmp_path / "bom.log", prefix + text.encode())
    seq = read_sequence(path)
    assert seq.stamps.tolist() == [1.0, 2.0, 3.0]  # the audit lost the first scan to a BOM


# --- defect 16: relations -------------------------------------------------------------------------


def test_repeated_relation_lines_count_once(tmp_path, caplog):
    line = "1.0 2.0 0.5 0 0 0 0 0.1\n"
    path = write(tmp_path / "r.relations", "\ufeff" + "0.5 1.0 0 0 0 0 0 0\n" + line * 50)
    with caplog.at_level(logging.WARNING, logger="scanguard.io"):
        rel = read_relations(path)
    assert rel.t1.tolist() == [0.5, 1.0] and rel.t2.tolist() == [1.0, 2.0]
    np.testing.assert_allclose(rel.delta[1], [0.5, 0.0, 0.1])
    assert any("49 repeated relation line(s)" in m for m in warnings_of(caplog))


def test_relation_with_equal_times_and_motion_is_refused(tmp_path):
    path = write(tmp_path / "r.relations", "0.5 1.0 0 0 0 0 0 0\n3.0 3.0 1.0 0 0 0 0 0\n")
    with pytest.raises(FormatError) as err:
        read_relations(path)
    assert "r.relations, line 2: t1 = t2 = 3.000000 s but the relation moves" in one_line(err.value)
    assert len(read_relations(path, lenient=True)) == 1
    still = write(tmp_path / "s.relations", "3.0 3.0 0 0 0 0 0 0\n")
    assert len(read_relations(still)) == 1  # no motion in no time is fine
