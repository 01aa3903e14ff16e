import numpy as np
import pytest

from scanguard import geometry as g


def test_compose_inverse_identity():
    rng = np.random.default_rng(1)
    a = np.column_stack([rng.normal(size=50), rng.normal(size=50), rng.uniform(-4, 4, 50)])
    ident = g.compose(a, g.inverse(a))
    np.testing.assert_allclose(ident, 0.0, atol=1e-12)


def test_relative_recovers_step():
    a = np.array([1.0, 2.0, 0.5])
    step = np.array([0.3, -0.1, 0.2])
    b = g.compose(a, step)
    np.testing.assert_allclose(g.relative(a, b), step, atol=1e-12)


def test_transform_points_matches_matrix():
    pose = np.array([0.5, -1.0, np.pi / 3])
    pts = np.array([[1.0, 0.0], [0.0, 2.0], [-1.0, -1.0]])
    m = g.pose_to_matrix(pose)
    expected = (m @ np.column_stack([pts, np.ones(3)]).T).T[:, :2]
    np.testing.assert_allclose(g.transform_points(pose, pts), expected, atol=1e-12)
    np.testing.assert_allclose(g.matrix_to_pose(m), pose, atol=1e-12)


def test_transform_points_keeps_float32():
    out = g.transform_points([0, 0, 0.1], np.ones((4, 2), dtype=np.float32))
    assert out.dtype == np.float32


@pytest.mark.parametrize("theta", [0.0, 3.0, -3.0, 7.0, -7.0, np.pi])
def test_wrap_and_quaternion(theta):
    w = g.wrap_angle(theta)
    assert -np.pi <= w < np.pi
    assert np.isclose(np.cos(w), np.cos(theta)) and np.isclose(np.sin(w), np.sin(theta))
    yaw = g.quaternion_to_yaw(g.yaw_to_quaternion(theta))
    assert np.isclose(g.wrap_angle(yaw - theta), 0.0, atol=1e-12) or np.isclose(
        abs(g.wrap_angle(yaw - theta)), 2 * np.pi, atol=1e-12
    )


def test_interpolate_poses_across_wrap():
    stamps = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, 0.0, -np.pi + 0.1]])
    mid = g.interpolate_poses(stamps, poses, [0.5, -1.0, 2.0])
    assert np.isclose(mid[0, 0], 1.0)
    assert np.isclose(abs(mid[0, 2]), np.pi)  # shortest arc goes through pi, not through 0
    np.testing.assert_allclose(mid[1], poses[0])
    np.testing.assert_allclose(mid[2], poses[1])


def test_pose_error():
    t, r = g.pose_error([1.0, 0.0, 0.1], [1.0, 0.05, 0.0])
    assert np.isclose(t, 0.05, atol=1e-3) and np.isclose(r, 0.1)


def test_single_pose_fast_path_is_bit_identical_to_the_array_form():
    """One pose at a time takes a scalar path: the same bits as the batched numpy forms."""
    rng = np.random.default_rng(11)
    a = rng.uniform(-50.0, 50.0, (4000, 3))
    b = rng.uniform(-50.0, 50.0, (4000, 3))
    a[:, 2] = rng.uniform(-40.0, 40.0, 4000)  # angles far outside [-pi, pi) wrap too
    a[:8, 2] = [np.pi, -np.pi, 0.0, -0.0, 1e-300, 3 * np.pi, -3 * np.pi, 2 * np.pi]
    batch_c, batch_i, batch_r = g.compose(a, b), g.inverse(a), g.relative(a, b)
    one_c = np.array([g.compose(x, y) for x, y in zip(a, b, strict=True)])
    one_i = np.array([g.inverse(x) for x in a])
    one_r = np.array([g.relative(x, y) for x, y in zip(a, b, strict=True)])
    assert one_c.tobytes() == batch_c.tobytes()
    assert one_i.tobytes() == batch_i.tobytes()
    assert one_r.tobytes() == batch_r.tobytes()
    # lists, float32 and a non-finite angle still take the array path, with its answers
    with np.errstate(invalid="ignore"):
        assert g.compose(np.array([0.0, 0.0, np.inf]), np.ones(3)).shape == (3,)
        assert np.isnan(g.inverse(np.array([1.0, 2.0, np.nan]))).all()
    listed = g.compose([1.0, 2.0, 0.5], list(b[0]))
    assert listed.tobytes() == g.compose(np.array([1.0, 2.0, 0.5]), b[0]).tobytes()
