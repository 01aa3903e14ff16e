"""Readers/writers: known figures of the real recordings, round trips and bad input."""

from __future__ import annotations

import gzip
import math
import re
from pathlib import Path

import numpy as np
import pytest

from scanguard.errors import FormatError, InputError, UnknownFormatError
from scanguard.geometry import wrap_angle
from scanguard.io import (
    READERS,
    Reader,
    get_reader,
    read_sequence,
    read_tum,
    summarize,
    write_sequence,
    write_tum,
)
from scanguard.io.carmen import CarmenReader
from scanguard.io.rosbag import RosbagReader
from scanguard.scan import ScanSequence
from tests.helpers import RPLIDAR, make_sequence, room_segments

DATA = Path(__file__).resolve().parent / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
INTEL_EXCERPT = DATA / "intel-corrected-excerpt.log.gz"
CCNY_EXCERPT = DATA / "ccny-excerpt.bag"
needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="shared data not present")


def _synthetic(n: int = 12, odometry: bool = True) -> ScanSequence:
    rng = np.random.default_rng(3)
    steps = np.column_stack(
        [rng.uniform(0.05, 0.2, n - 1), rng.normal(0, 0.03, n - 1), rng.normal(0, 0.05, n - 1)]
    )
    seq = make_sequence(room_segments(), steps, start=(-2.0, 0.5, 0.3), noise=0.01, seed=1)
    # an epoch-like start exercises the nanosecond split of stamps
    scans = [s.with_ranges(s.ranges, stamp=1.7e9 + s.stamp) for s in seq.scans]
    ranges = scans[3].ranges.copy()
    ranges[:5] = [np.nan, np.inf, -np.inf, 0.0, 99.0]
    scans[3] = scans[3].with_ranges(ranges)
    odo = None
    if odometry:
        odo = seq.reference + rng.normal(0, 0.05, seq.reference.shape)
        odo[:, 2] = wrap_angle(odo[:, 2])
    return ScanSequence(
        name="room",
        scans=scans,
        sensor=RPLIDAR,
        odometry=odo,
        reference=seq.reference,
        reference_kind="ground_truth",
        laser_offset=np.array([0.12, -0.03, 0.05]),
        metadata={"scenario": "room", "seed": 1, "frame_id": "lidar", "source": "unit-test"},
    )


def _assert_same(a: ScanSequence, b: ScanSequence) -> None:
    assert len(a) == len(b)
    np.testing.assert_allclose(a.stamps, b.stamps, rtol=0, atol=1e-6)
    for sa, sb in zip(a.scans, b.scans, strict=True):
        np.testing.assert_array_equal(sa.ranges, sb.ranges)
        assert sa.same_geometry(sb, atol=1e-6)
        np.testing.assert_array_equal(sa.valid, sb.valid)
    for pa, pb in ((a.odometry, b.odometry), (a.reference, b.reference)):
        assert (pa is None) == (pb is None)
        if pa is not None:
            np.testing.assert_allclose(pa[:, :2], pb[:, :2], atol=1e-9)
            np.testing.assert_allclose(wrap_angle(pa[:, 2] - pb[:, 2]), 0, atol=1e-9)
    np.testing.assert_allclose(a.laser_offset, b.laser_offset, atol=1e-9)
    assert a.reference_kind == b.reference_kind


# --- registry ---------------------------------------------------------------------------------


def test_registry_by_extension_and_format(tmp_path):
    assert all(isinstance(r, Reader) for r in READERS.values())
    assert isinstance(READERS[".bag"], RosbagReader)
    assert isinstance(READERS[".mcap"], RosbagReader)
    assert isinstance(READERS[".log.gz"], CarmenReader)
    assert isinstance(get_reader("x/intel.LOG.GZ"), CarmenReader)
    assert isinstance(get_reader("x/whatever.gz", format="carmen"), CarmenReader)
    assert isinstance(get_reader("x/whatever", format=".bag"), RosbagReader)
    with pytest.raises(UnknownFormatError, match=r"whatever\.txt.*'\.txt'"):
        get_reader("whatever.txt")
    with pytest.raises(UnknownFormatError, match="unknown format 'velodyne'"):
        get_reader("a.bag", format="velodyne")
    odd = tmp_path / "scans.txt"
    odd.write_text("x")
    with pytest.raises(UnknownFormatError, match=re.escape(str(odd))):
        read_sequence(odd)
    with pytest.raises(InputError, match=r"missing\.bag: file not found"):
        read_sequence(tmp_path / "missing.bag")


# --- CARMEN -----------------------------------------------------------------------------------


def test_carmen_excerpt_known_figures():
    seq = read_sequence(INTEL_EXCERPT)
    assert len(seq) == 100
    s = summarize(seq)
    assert s["beams"] == [180]
    assert math.isclose(s["fov_deg"], 180.0, abs_tol=1e-9)
    assert seq.sensor.angle_min == pytest.approx(-np.pi / 2)
    assert seq.scans[0].angle_max == pytest.approx(np.pi / 2)
    assert s["range_max"] == 80.0
    # corrected log: embedded pose is the reference, ODOM lines are not used as odometry
    assert seq.reference_kind == "corrected_log"
    assert seq.odometry is None
    # first FLASER line: "FLASER 180 1.09 1.08 1.08 ... 1.23 0.600266 -0.0320327 -0.354665 ..."
    first = seq.scans[0]
    assert first.ranges[:3].tolist() == pytest.approx([1.09, 1.08, 1.08])
    assert first.ranges[-1] == pytest.approx(1.23)
    np.testing.assert_allclose(seq.reference[0], [0.600266, -0.0320327, -0.354665])
    assert first.stamp == pytest.approx(32.9068)
    # 81.83 m is SICK's no-return code: stored as +inf and invalid
    all_r = np.concatenate([sc.ranges for sc in seq.scans])
    assert np.isinf(all_r).sum() > 0 and not np.any((all_r > 80) & np.isfinite(all_r))
    assert seq.metadata["topics"]["FLASER"]["count"] == 100


def test_carmen_explicit_odometry_sources():
    odom = read_sequence(INTEL_EXCERPT, odom_topic="ODOM")
    assert odom.odometry is not None and odom.metadata["odometry_source"] == "ODOM lines"
    # ODOM lines of this corrected log start at the origin and are not the corrected poses
    assert np.abs(odom.odometry - odom.reference).max() > 0.5
    embedded = read_sequence(INTEL_EXCERPT, odom_topic="laser")
    np.testing.assert_allclose(embedded.odometry, embedded.reference)
    with pytest.raises(InputError, match=r"topic RLASER.*FLASER"):
        read_sequence(INTEL_EXCERPT, scan_topic="RLASER")


def _carmen_lines() -> list[str]:
    return gzip.decompress(INTEL_EXCERPT.read_bytes()).decode().splitlines(keepends=True)


def test_carmen_garbled_line_names_file_and_line(tmp_path):
    lines = _carmen_lines()
    idx = next(i for i, ln in enumerate(lines) if ln.startswith("FLASER"))
    tokens = lines[idx].split()
    tokens[7] = "1.2x"
    lines[idx] = " ".join(tokens) + "\n"
    bad = tmp_path / "garbled-corrected.log"
    bad.write_text("".join(lines))
    with pytest.raises(FormatError, match=rf"garbled-corrected\.log, line {idx + 1}: .*'1\.2x'"):
        read_sequence(bad)

    lines = _carmen_lines()
    lines[idx] = " ".join(lines[idx].split()[:50]) + "\n"  # cut in the middle of the ranges
    bad.write_text("".join(lines))
    with pytest.raises(FormatError, match=rf"line {idx + 1}: FLASER: truncated line"):
        read_sequence(bad)


def test_carmen_truncated_gzip(tmp_path):
    raw = INTEL_EXCERPT.read_bytes()
    bad = tmp_path / "cut-corrected.log.gz"
    bad.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FormatError, match=r"cut-corrected\.log\.gz: truncated gzip"):
        read_sequence(bad)


def test_carmen_zero_beams_and_no_laser(tmp_path):
    zero = tmp_path / "zero.log"
    zero.write_text("ODOM 0 0 0 0 0 0 1.0 host 1.0\nFLASER 0 0 0 0 0 0 0 2.0 host 2.0\n")
    with pytest.raises(FormatError, match=r"zero\.log, line 2: FLASER: .*zero-beam"):
        read_sequence(zero)
    none = tmp_path / "odom-only.log"
    none.write_text("ODOM 0 0 0 0 0 0 1.0 host 1.0\n")
    with pytest.raises(InputError, match=r"no laser lines.*ODOM \(1\)"):
        read_sequence(none)


def test_carmen_robotlaser_and_clip_code(tmp_path):
    n = 5
    ranges = [1.0, 2.0, 50.0, np.nan, 3.0]
    lines = []
    for k in range(3):
        r = " ".join("nan" if np.isnan(v) else f"{v}" for v in ranges)
        # type start fov res maxrange acc mode n ranges n_rem laser(3) robot(3) 5 values stamp
        lines.append(
            f"ROBOTLASER1 0 -1.0 2.0 0.5 50.0 0.01 0 {n} {r} 0 "
            f"{k + 0.1} 0.0 0.0 {k} 0.0 0.0 0 0 0 0 0 {10.0 + k} host {10.0 + k}\n"
        )
    log = tmp_path / "robot.clf"
    log.write_text("".join(lines))
    seq = read_sequence(log)
    assert seq.odometry is not None and seq.reference is None  # raw log
    s0 = seq.scans[0]
    assert (s0.angle_min, s0.angle_increment, s0.range_max) == (-1.0, 0.5, 50.0)
    assert s0.valid.tolist() == [True, True, False, False, True]
    np.testing.assert_allclose(seq.laser_offset, [0.1, 0.0, 0.0])
    np.testing.assert_allclose(seq.odometry[:, 0], [0, 1, 2])
    assert seq.rate_hz == pytest.approx(1.0)

    # FLASER log whose no-returns are clipped to 50 m (as in ACES): detected, become inf
    body = ["FLASER 4 1.5 50 50 2.5 0 0 0 0 0 0 1.0 h 1.0\n"] * 3
    clip = tmp_path / "clip.log"
    clip.write_text("".join(body))
    seq = read_sequence(clip)
    assert seq.sensor.range_max == 50.0
    assert seq.scans[0].valid.tolist() == [True, False, False, True]
    seq = read_sequence(clip, reader_options={"max_range": 60.0})
    assert seq.scans[0].valid.tolist() == [True, True, True, True]
    with pytest.raises(InputError, match="unknown carmen reader option"):
        read_sequence(clip, reader_options={"fov": 3})


@needs_shared
@pytest.mark.parametrize(
    ("name", "scans", "beams", "range_max"),
    [
        ("intel-corrected.log.gz", 910, 180, 80.0),
        ("aces-corrected.log.gz", 440, 180, 50.0),
        ("csail-corrected.log.gz", 406, 361, 80.0),
        ("freiburg-079-corrected.log.gz", 4791, 360, 80.0),
    ],
)
def test_shared_carmen_logs(name, scans, beams, range_max):
    seq = read_sequence(SHARED / "carmen" / name)
    s = summarize(seq)
    assert s["scans"] == scans
    assert s["beams"] == [beams]
    assert s["fov_deg"] == pytest.approx(180.0)
    assert s["range_max"] == range_max
    assert seq.reference_kind == "corrected_log" and seq.odometry is None
    if name.startswith("csail"):  # stamps written as 1.13486e+09
        assert s["rate_hz"] is None and "rounded" in s["stamps_note"]
    if name.startswith("intel"):
        excerpt = read_sequence(INTEL_EXCERPT)
        _assert_same(excerpt, seq.subsequence(slice(0, 100)))


# --- ROS bags ---------------------------------------------------------------------------------


def test_ros1_excerpt_known_figures():
    seq = read_sequence(CCNY_EXCERPT)
    s = summarize(seq)
    assert s["scans"] == 60 and s["beams"] == [681]
    assert s["fov_deg"] == pytest.approx(239.06, abs=0.01)
    assert s["range_max"] == pytest.approx(5.6)
    assert s["rate_hz"] == pytest.approx(10.0, rel=0.01)
    assert not s["odometry"] and not s["reference"]
    assert s["topics"] == {"/scan": {"type": "sensor_msgs/msg/LaserScan", "count": 60}}
    # header stamp of the first message: 1282836370.970876375
    assert seq.scans[0].stamp == pytest.approx(1282836370.970876375, abs=1e-6)
    assert seq.metadata["frame_id"] == "laser"


@needs_shared
def test_shared_bags():
    ccny = read_sequence(SHARED / "rosbag" / "ccny_laser_scan_matcher_demo.bag")
    s = summarize(ccny)
    assert (s["scans"], s["beams"]) == (360, [681])
    assert round(s["fov_deg"]) == 239 and s["range_max"] == pytest.approx(5.6)
    _assert_same(read_sequence(CCNY_EXCERPT), ccny.subsequence(slice(0, 60)))
    leg = read_sequence(SHARED / "rosbag" / "leg_tracker_positive_1.bag", reference="static")
    s = summarize(leg)
    assert (s["scans"], s["beams"], s["range_max"]) == (400, [768], 11.0)
    assert round(s["fov_deg"]) == 270
    assert leg.reference_kind == "static" and np.all(leg.reference == 0)


@pytest.mark.parametrize("target", ["seq.mcap", "bagdir"])
def test_mcap_round_trip(tmp_path, target):
    seq = _synthetic()
    out = write_sequence(seq, tmp_path / target)
    assert out == tmp_path / target
    back = read_sequence(out)
    _assert_same(seq, back)
    assert back.name == "room" and back.metadata["scenario"] == "room"
    assert back.metadata["source"] == "unit-test" and back.metadata["path"] == str(out)
    assert back.sensor.name == RPLIDAR.name
    assert back.metadata["frame_id"] == "lidar"
    assert set(back.metadata["topics"]) >= {"/scan", "/odom", "/ground_truth", "/tf_static"}
    # NaN / inf / out-of-range beams survive unchanged and stay invalid
    r = back.scans[3].ranges
    assert np.isnan(r[0]) and r[1] == np.inf and r[2] == -np.inf
    assert not back.scans[3].valid[:5].any()
    if target == "bagdir":
        assert (out / "metadata.yaml").is_file()
        _assert_same(seq, read_sequence(out / "bagdir.mcap"))  # the file inside the folder
        write_sequence(seq.subsequence(slice(0, 4)), out)  # replaces the old bag
        assert len(read_sequence(out)) == 4
    else:
        assert out.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [target]  # no temp leftovers


def test_written_bag_topics_are_picked_and_checked(tmp_path):
    seq = _synthetic(6)
    out = write_sequence(seq, tmp_path / "a.mcap", reference_topic="/base_pose_ground_truth")
    back = read_sequence(out)
    assert back.metadata["reference_source"] == "/base_pose_ground_truth"
    with pytest.raises(InputError, match=r"topic /nope: no odometry topic '/nope'.*/odom"):
        read_sequence(out, odom_topic="/nope")
    with pytest.raises(InputError, match="odometry topic has type sensor_msgs/msg/LaserScan"):
        read_sequence(out, odom_topic="/scan")


def test_converted_ros1_bag_reads_the_same(tmp_path):
    from rosbags.convert import convert

    dst = tmp_path / "ccny_ros2"
    convert([CCNY_EXCERPT], dst, "mcap", 9, None, "none", None, None, [], [], [], [])
    _assert_same(read_sequence(CCNY_EXCERPT), read_sequence(dst))
    dst2 = tmp_path / "ccny_sqlite"
    convert([CCNY_EXCERPT], dst2, "sqlite3", 8, None, "none", None, None, [], [], [], [])
    _assert_same(read_sequence(CCNY_EXCERPT), read_sequence(dst2))


def _ros1_bag(
    path: Path, scans: list[tuple[float, np.ndarray]], odom_topics: tuple[str, ...] = ("/odom",)
) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    with Writer(path) as w:
        for k, topic in enumerate(odom_topics):
            c = w.add_connection(topic, "nav_msgs/msg/Odometry", typestore=ts)
            msg = T["nav_msgs/msg/Odometry"](
                header=T["std_msgs/msg/Header"](
                    seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="o"
                ),
                child_frame_id="b",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=T["geometry_msgs/msg/Pose"](
                        position=T["geometry_msgs/msg/Point"](x=float(k), y=0.0, z=0.0),
                        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                    covariance=np.zeros(36),
                ),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](
                        linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    ),
                    covariance=np.zeros(36),
                ),
            )
            w.write(c, 10**9, ts.serialize_ros1(msg, "nav_msgs/msg/Odometry"))
        if scans:
            c = w.add_connection("/base_scan", "sensor_msgs/msg/LaserScan", typestore=ts)
            for stamp, ranges in scans:
                msg = T["sensor_msgs/msg/LaserScan"](
                    header=T["std_msgs/msg/Header"](
                        seq=0,
                        stamp=T["builtin_interfaces/msg/Time"](
                            sec=int(stamp), nanosec=round((stamp % 1) * 1e9)
                        ),
                        frame_id="laser",
                    ),
                    angle_min=-1.0,
                    angle_max=1.0,
                    angle_increment=0.5,
                    time_increment=0.0,
                    scan_time=0.1,
                    range_min=0.1,
                    range_max=10.0,
                    ranges=np.asarray(ranges, dtype=np.float32),
                    intensities=np.zeros(0, dtype=np.float32),
                )
                w.write(c, int(stamp * 1e9), ts.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))


def test_bag_without_laserscan_names_topics(tmp_path):
    bag = tmp_path / "odom_only.bag"
    _ros1_bag(bag, [])
    with pytest.raises(
        InputError,
        match=r"odom_only\.bag: no sensor_msgs/LaserScan topic; "
        r"topics found: /odom \(nav_msgs/msg/Odometry\)",
    ):
        read_sequence(bag)


def test_bag_nan_inf_ranges_and_zero_beams(tmp_path):
    bag = tmp_path / "weird.bag"
    _ros1_bag(bag, [(1.0, [1.0, np.nan, np.inf, 20.0, 2.0]), (1.1, [1.0, 2.0, 3.0, 4.0, 5.0])])
    seq = read_sequence(bag)
    assert seq.scans[0].valid.tolist() == [True, False, False, False, True]
    assert seq.odometry is not None  # the only Odometry topic is auto-picked
    np.testing.assert_allclose(seq.odometry, 0.0)
    assert seq.invalid_fraction == pytest.approx(3 / 10)
    empty = tmp_path / "empty_scan.bag"
    _ros1_bag(empty, [(1.0, [1.0, 2.0, 3.0, 4.0, 5.0]), (1.1, [])])  # 5 beams: -1..1 rad at 0.5
    with pytest.raises(FormatError, match=r"empty_scan\.bag, topic /base_scan: message 1: .*zero"):
        read_sequence(empty)


def test_garbled_bag(tmp_path):
    bad = tmp_path / "bad.bag"
    bad.write_bytes(CCNY_EXCERPT.read_bytes()[:5000])
    with pytest.raises(FormatError, match=r"bad\.bag: cannot read bag"):
        read_sequence(bad)


# --- TUM / static reference ---------------------------------------------------------------------


def test_tum_round_trip_and_reference(tmp_path):
    seq = _synthetic(odometry=False)
    path = write_tum(tmp_path / "gt.tum", seq.stamps, seq.reference)
    stamps, poses = read_tum(path)
    np.testing.assert_allclose(stamps, seq.stamps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(poses[:, :2], seq.reference[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap_angle(poses[:, 2] - seq.reference[:, 2]), 0, atol=1e-12)
    first = path.read_text().splitlines()[1].split()
    assert len(first) == 8 and float(first[3]) == 0.0  # z = 0, evo-compatible layout

    bag = write_sequence(seq, tmp_path / "s.mcap")
    plain = read_sequence(bag)
    plain.reference = None
    # a TUM file as reference for any recording, interpolated to the scan stamps
    mid = (seq.stamps[:-1] + seq.stamps[1:]) / 2
    from scanguard.geometry import interpolate_poses

    write_tum(tmp_path / "half.tum", mid, interpolate_poses(seq.stamps, seq.reference, mid))
    with_ref = read_sequence(bag, reference=tmp_path / "half.tum")
    assert with_ref.reference_kind == "tum"
    np.testing.assert_allclose(with_ref.reference[1:-1, :2], seq.reference[1:-1, :2], atol=0.05)
    static = read_sequence(bag, reference="static")
    assert static.reference_kind == "static" and np.all(static.reference == 0)


def test_tum_bad_input(tmp_path):
    p = tmp_path / "bad.tum"
    p.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"bad\.tum, line 3: expected 8 values"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 zero 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"line 2: not a number"):
        read_tum(p)
    p.write_text("100.0 0 0 0 0 0 0 1\n101.0 0 0 0 0 0 0 1\n")
    seq = _synthetic(4, odometry=False)
    out = write_sequence(seq, tmp_path / "s.mcap")
    with pytest.raises(InputError, match="no overlap"):
        read_sequence(out, reference=p)


def test_foreign_bag_odometry_and_reference_auto_pick(tmp_path):
    scans = [(1.0, [1.0, 2.0, 3.0, 4.0, 5.0]), (1.1, [1.0, 2.0, 3.0, 4.0, 5.0])]
    bag = tmp_path / "gt.bag"
    _ros1_bag(bag, scans, odom_topics=("/odom", "/ground_truth"))
    seq = read_sequence(bag)
    assert seq.metadata["odometry_source"] == "/odom"
    assert seq.metadata["reference_source"] == "/ground_truth"
    np.testing.assert_allclose(seq.reference[:, 0], 1.0)
    np.testing.assert_allclose(seq.odometry[:, 0], 0.0)
    two = tmp_path / "two.bag"
    _ros1_bag(two, scans, odom_topics=("/odom", "/wheel_odom"))
    seq = read_sequence(two)
    assert seq.odometry is None and seq.reference is None  # ambiguous: nothing guessed
    seq = read_sequence(two, odom_topic="wheel_odom", reference_topic="/odom")
    np.testing.assert_allclose(seq.odometry[:, 0], 1.0)
    assert seq.reference_kind == "ground_truth"


def test_laser_offset_from_tf_static_without_info_record(tmp_path):
    from rosbags.convert import convert

    seq = _synthetic(5)
    src = write_sequence(seq, tmp_path / "with_info")
    dst = tmp_path / "no_info"
    convert([src], dst, "mcap", 9, None, "none", None, None, ["/scanguard/info"], [], [], [])
    back = read_sequence(dst)
    assert "/scanguard/info" not in back.metadata["topics"]
    np.testing.assert_allclose(back.laser_offset, seq.laser_offset, atol=1e-9)
    assert back.metadata["reference_source"] == "/ground_truth"  # picked by its name
    assert back.metadata["odometry_source"] == "/odom"  # the only other Odometry topic
    assert back.sensor.name == "lidar"  # frame id when no sensor name is recorded
