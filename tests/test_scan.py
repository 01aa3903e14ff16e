import numpy as np
import pytest

from scanguard.errors import ScanError
from scanguard.scan import LaserScan, ScanSequence
from tests.helpers import RPLIDAR, make_scan, room_segments


def test_invalid_beams_never_become_points():
    r = np.array([1.0, np.nan, np.inf, -np.inf, 0.01, 30.0, 2.0], dtype=np.float32)
    s = LaserScan(0.0, r, angle_min=0.0, angle_increment=0.1, range_min=0.1, range_max=25.0)
    np.testing.assert_array_equal(s.valid, [True, False, False, False, False, False, True])
    pts = s.points()
    assert pts.shape == (2, 2)
    assert np.all(np.isfinite(pts))
    np.testing.assert_allclose(pts[1], [2 * np.cos(0.6), 2 * np.sin(0.6)], rtol=1e-6)
    assert np.isclose(s.invalid_fraction, 5 / 7)


def test_zero_beam_scan_is_an_error():
    with pytest.raises(ScanError, match="zero beams"):
        LaserScan(1.5, np.array([]), angle_min=0.0, angle_increment=0.1, range_min=0, range_max=1)


def test_points_of_known_room():
    scan = make_scan(room_segments(), (0.0, 0.0, 0.0))
    beam0 = scan.points(np.float64)  # beam at -pi hits the left wall at x = -5
    assert np.isclose(scan.ranges[0], 5.0, atol=1e-5)
    assert np.isclose(beam0[0, 0], -5.0, atol=1e-4)


def test_sequence_properties_and_subsequence():
    scans = [make_scan(room_segments(), (0.1 * i, 0, 0), stamp=0.1 * i) for i in range(5)]
    ref = np.array([[0.1 * i, 0, 0] for i in range(5)])
    seq = ScanSequence("room", scans, reference=ref)
    assert seq.sensor is not None and seq.sensor.n_beams == RPLIDAR.n_beams
    assert np.isclose(seq.rate_hz, 10.0)
    assert np.isclose(seq.duration, 0.4)
    sub = seq.subsequence([1, 3])
    assert len(sub) == 2 and np.allclose(sub.reference[:, 0], [0.1, 0.3])
    assert seq.ranges_matrix().shape == (5, 1440)
    with pytest.raises(ScanError, match="shape"):
        ScanSequence("bad", scans, odometry=np.zeros((4, 3)))


def test_derived_arrays_are_cached_read_only_and_independent_of_the_input():
    raw = np.array([1.0, 2.0, np.nan, 4.0], dtype=np.float32)
    scan = LaserScan(
        stamp=0.0, ranges=raw, angle_min=0.0, angle_increment=0.5, range_min=0.1, range_max=10
    )
    pts = scan.points(np.float64)
    # one computation per scan and dtype, shared by every caller (ICP, images, features)
    assert scan.points(np.float64) is pts and scan.points(np.float32) is not pts
    np.testing.assert_allclose(pts[1], [2.0 * np.cos(0.5), 2.0 * np.sin(0.5)])
    assert len(pts) == 3  # the NaN beam is not a point
    for arr in (pts, scan.ranges, scan.valid, scan.angles):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 0
    # the scan owns its ranges: changing the caller's buffer changes nothing
    raw[0] = 9.0
    assert scan.ranges[0] == 1.0 and scan.points(np.float64)[0, 0] == 1.0


def test_a_pickled_scan_is_the_measurement_without_its_cached_arrays():
    import pickle

    ranges = np.array([1.0, np.nan, 2.5, -1.0], dtype=np.float32)
    scan = LaserScan(3.25, ranges, -0.5, 0.25, -0.1, 4.0, intensities=np.arange(4.0))
    points = scan.points(np.float64)  # cached now
    data = pickle.dumps(scan)
    assert len(data) < len(pickle.dumps(scan.ranges)) + 600  # the cache does not travel
    back = pickle.loads(data)
    assert (back.stamp, back.angle_min, back.angle_increment) == (3.25, -0.5, 0.25)
    assert (back.range_min, back.range_max) == (0.0, 4.0)  # validated again: -0.1 read as 0
    np.testing.assert_array_equal(back.ranges, ranges)
    np.testing.assert_array_equal(back.intensities, np.arange(4.0))
    assert not back.ranges.flags.writeable
    np.testing.assert_array_equal(back.points(np.float64), points)  # recomputed identically
