"""Back ends: the `frontend` chain (known answers, parity with `ScanGuard`), the protocol."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from scanguard.geometry import compose, relative, transform_points
from scanguard.scan import LaserScan
from scanguard.slam.backend import Backend, FrontendBackend
from scanguard.slam.grid import chain
from scanguard.slam.guard import GuardConfig
from scanguard.slam.stream import ScanGuard
from tests.helpers import make_sequence, room_segments

OFFSET = np.array([0.3, 0.1, 0.2])


class AlignmentDetector:
    """Geometric stand-in for the CNN: fault when the median NN distance exceeds 5 cm."""

    threshold = 0.5

    def fault_probability(self, previous: LaserScan, current: LaserScan, pose) -> float:
        moved = transform_points(np.asarray(pose), current.points(np.float64))
        d, _ = cKDTree(previous.points(np.float64)).query(moved)
        return float(np.median(d) > 0.05)


@pytest.fixture(scope="module")
def room():
    rng = np.random.default_rng(5)
    steps = np.column_stack(
        [rng.uniform(0.05, 0.12, 12), rng.uniform(-0.03, 0.03, 12), rng.uniform(-0.05, 0.05, 12)]
    )
    seq = make_sequence(room_segments(), steps, start=(-2.0, -0.5, 0.1))
    # drifting odometry with its own start: only its increments may be used
    inc = relative(seq.reference[:-1], seq.reference[1:]) + np.array([0.01, -0.004, 0.003])
    seq.odometry = chain((5.0, 1.0, -0.3), inc)
    return seq


@pytest.fixture(scope="module")
def lobby():
    from scanguard.sim import simulate

    return simulate("lobby", seed=3, duration=3.0)


def test_frontend_is_a_backend():
    fe = FrontendBackend()
    assert isinstance(fe, Backend)
    assert fe.name == "frontend"
    assert fe.wants_scan(0.0, None) and fe.wants_scan(1.0, np.zeros(3))
    assert fe.trajectory().shape == (0, 3) and fe.used().shape == (0,)


def test_frontend_never_usable_follows_odometry_exactly(room):
    start = np.array([1.0, 2.0, 0.5])
    fe = FrontendBackend(laser_offset=OFFSET, initial_pose=start)
    bogus = np.array([3.0, -2.0, 1.0])  # a match that must be ignored on unusable scans
    for scan, odo in zip(room.scans, room.odometry, strict=True):
        fe.update(scan, odo, usable=False, match=bogus)
    expected = chain(start, relative(room.odometry[:-1], room.odometry[1:]))
    np.testing.assert_allclose(fe.trajectory(), expected, atol=1e-12)
    np.testing.assert_array_equal(fe.pose, expected[-1])
    assert not fe.used().any()
    grid = fe.grid()
    assert grid is not None and not grid.known_mask().any()  # nothing inserted


def test_frontend_exact_matches_give_the_reference(room):
    """Usable scans with exact sensor-frame matches chain to the exact robot poses."""
    laser = compose(room.reference, OFFSET)
    truth = relative(laser[:-1], laser[1:])
    fe = FrontendBackend(laser_offset=OFFSET, initial_pose=room.reference[0])
    fe.update(room.scans[0], room.odometry[0], usable=True, match=None)
    for k in range(1, len(room)):
        fe.update(room.scans[k], room.odometry[k], usable=True, match=truth[k - 1])
    np.testing.assert_allclose(fe.trajectory(), room.reference, atol=1e-9)
    assert fe.used().all()
    # a usable scan whose match failed (None or NaN) moves by odometry and is not mapped
    fe2 = FrontendBackend(initial_pose=room.reference[0])
    fe2.update(room.scans[0], room.odometry[0])
    fe2.update(room.scans[1], room.odometry[1], usable=True, match=np.full(3, np.nan))
    fe2.update(room.scans[2], room.odometry[2], usable=True, match=None)
    odo_inc = relative(room.odometry[:-1], room.odometry[1:])
    np.testing.assert_allclose(fe2.trajectory(), chain(room.reference[0], odo_inc[:2]), atol=1e-12)
    np.testing.assert_array_equal(fe2.used(), [True, False, False])


@pytest.mark.parametrize("prior", ["constant_position", "constant_velocity"])
def test_frontend_priors_without_odometry(room, prior):
    laser = compose(room.reference, OFFSET)
    truth = relative(laser[:-1], laser[1:])
    robot_truth = relative(room.reference[:-1], room.reference[1:])
    start = room.reference[0]
    fe = FrontendBackend(laser_offset=OFFSET, initial_pose=start, motion_prior=prior)
    fe.update(room.scans[0], None)
    fe.update(room.scans[1], None, usable=True, match=truth[0])  # accepted: moves by step 0
    for k in (2, 3, 4):
        fe.update(room.scans[k], None, usable=False)  # rejected, no odometry: the prior
    step = robot_truth[0] if prior == "constant_velocity" else np.zeros(3)
    expected = chain(start, [robot_truth[0], step, step, step])
    np.testing.assert_allclose(fe.trajectory(), expected, atol=1e-9)
    np.testing.assert_array_equal(fe.used(), [True, True, False, False, False])


def test_frontend_rejects_an_unknown_prior():
    from scanguard.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown motion prior"):
        FrontendBackend(motion_prior="teleport")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("policy", "odometry", "fallback"),
    [
        ("cnn", True, "constant_position"),
        ("none", True, "constant_position"),
        ("cnn", False, "constant_position"),
        ("cnn", False, "constant_velocity"),
    ],
)
def test_frontend_reproduces_scanguard_fusion(lobby, policy, odometry, fallback):
    """Fed the guard's verdicts, the frontend gives exactly the guard's poses and map."""
    from scanguard.matching import get_matcher

    cfg = GuardConfig(policy=policy, motion_prior=fallback)
    start = lobby.reference[0]
    guard = ScanGuard(
        AlignmentDetector(),
        get_matcher("icp-paper"),
        cfg,
        laser_offset=lobby.laser_offset,
        initial_pose=start,
    )
    fe = FrontendBackend(
        laser_offset=lobby.laser_offset, initial_pose=start, motion_prior=fallback, grid=cfg.grid
    )
    decisions = []
    for k, scan in enumerate(lobby.scans):
        odo = lobby.odometry[k] if odometry else None
        d = guard.step(scan, odo)
        decisions.append(d)
        match = None if d.match is None else np.asarray(d.match.pose)
        fe.update(scan, odo, usable=d.accepted, match=match)
    accepted = np.array([d.accepted for d in decisions])
    if policy == "cnn":  # the gate really rejects some scans of the crowded lobby
        assert 0 < (~accepted).sum() < len(lobby) - 1
    else:
        assert accepted.all()
    # the guard runs the loop of every run: without odometry its frontend is moved by the
    # loop's pseudo-odometry (the last increment composed onto a pose), this one by its own
    # prior (the increment applied): the same motion, rounded in another order (~1e-16 m)
    tol = 1e-12 if fallback == "constant_velocity" and not odometry else 0.0
    np.testing.assert_allclose(fe.trajectory(), np.array([d.pose for d in decisions]), atol=tol)
    np.testing.assert_array_equal(fe.used(), accepted)
    assert guard.grid is not None and fe.grid() is not None
    np.testing.assert_array_equal(fe.grid().logodds, guard.grid.logodds)
    np.testing.assert_array_equal(fe.grid().origin, guard.grid.origin)


def _gmapping():
    import scanguard.slam.gmapping as gm

    if not hasattr(gm, "GMappingBackend"):
        pytest.skip("the gmapping back end is not in this build yet")
    return gm


def test_make_backend_builds_independent_instances(room):
    from scanguard.slam.config import RunConfig
    from scanguard.slam.registry import make_backend

    a = make_backend(RunConfig(backend="frontend"), initial_pose=(1.0, 2.0, 0.0))
    b = make_backend(RunConfig(backend="frontend"), initial_pose=(1.0, 2.0, 0.0))
    assert isinstance(a, FrontendBackend) and a is not b
    a.update(room.scans[0], room.odometry[0])
    a.update(room.scans[1], room.odometry[1], usable=False)
    assert len(a.trajectory()) == 2 and len(b.trajectory()) == 0
    np.testing.assert_array_equal(b.pose, [1.0, 2.0, 0.0])


def test_make_backend_gmapping_is_seeded_and_a_backend(room):
    gm = _gmapping()
    from scanguard.slam.config import RunConfig
    from scanguard.slam.registry import make_backend

    cfg = RunConfig(backend="gmapping", gmapping=gm.GMappingConfig(particles=5, seed=11))
    runs = []
    for _ in range(2):
        be = make_backend(cfg, initial_pose=room.reference[0], range_max=25.0)
        assert isinstance(be, Backend) and be.name == "gmapping"
        for scan, odo in zip(room.scans, room.odometry, strict=True):
            be.update(scan, odo, usable=True)
        runs.append(be.trajectory())
    assert runs[0].shape == (len(room), 3)
    np.testing.assert_array_equal(runs[0], runs[1])  # same config and seed, same run
