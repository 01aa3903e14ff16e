"""Loop-closure trap scenarios: twin rooms, twin corridors and a crowd at the closing point."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from scanguard.errors import ConfigError
from scanguard.geometry import relative, wrap_angle
from scanguard.sim import (
    CLOSURE_TRAPS,
    GMAPPING_TRAPS,
    SCENARIOS,
    ScenarioConfig,
    SimulationResult,
    build_world,
    cast_rays,
    load_scenario,
    simulate_run,
)
from scanguard.sim.config import MaterialsConfig, PeopleConfig

SEED = 0
#: Fewer beams than the sensors have keep the full-length runs fast; the aliasing checks cast
#: their own full-resolution scans against the static world.
BEAMS = 271
_RUNS: dict[str, SimulationResult] = {}


def _run(name: str) -> SimulationResult:
    if name not in _RUNS:
        _RUNS[name] = simulate_run(name, seed=SEED, sensor__n_beams=BEAMS)
    return _RUNS[name]


def _static_points(res: SimulationResult, pose: np.ndarray) -> np.ndarray:
    """Noise-free scan of the static world (no people) from ``pose`` as world points."""
    info = res.config.sensor.info()
    ang = info.angle_min + info.angle_increment * np.arange(info.n_beams) + pose[2]
    w = res.world
    r = cast_rays(
        np.asarray(pose[:2], dtype=np.float64),
        ang,
        w.segments,
        w.segment_material,
        w.circles,
        w.circle_material,
        MaterialsConfig(),
        np.random.default_rng(0),
        max_range=info.range_max * 1.5,
    )
    ok = np.isfinite(r) & (r <= info.range_max)
    return np.column_stack([pose[0] + r[ok] * np.cos(ang[ok]), pose[1] + r[ok] * np.sin(ang[ok])])


def _mean_nn(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric mean nearest-neighbour distance between two point sets."""
    return 0.5 * (float(cKDTree(b).query(a)[0].mean()) + float(cKDTree(a).query(b)[0].mean()))


def _first_return(ref: np.ndarray, after: int = 200) -> int:
    d = np.hypot(*(ref[:, :2] - ref[0, :2]).T)
    idx = np.nonzero((d < 0.5) & (np.arange(len(ref)) > after))[0]
    assert idx.size, "the robot never comes back to its start"
    return int(idx[0])


def test_closure_traps_are_listed_loops_with_a_default_duration():
    assert CLOSURE_TRAPS == ("twin_rooms", "twin_corridors", "crowd_closure")
    assert not set(CLOSURE_TRAPS) & (set(SCENARIOS) | set(GMAPPING_TRAPS))
    for name in CLOSURE_TRAPS:
        cfg = load_scenario(name)
        assert cfg.name == name and cfg.duration is not None and 90 <= cfg.duration <= 180
        assert cfg.robot.mode == "route"
        assert 1.0 / cfg.scan_period() == pytest.approx(10.0)
        world = build_world(cfg.world, np.random.default_rng([5, 0]), name)
        np.testing.assert_allclose(world.route[-1], world.start[:2])


def test_gather_count_must_fit_the_crowd():
    with pytest.raises(ValueError, match="gather_count"):
        PeopleConfig(count=3, gather_count=4)
    with pytest.raises(ConfigError, match="rooms"):
        ScenarioConfig.from_dict(
            {"name": "x", "world": {"generator": "twin_rooms", "params": {"rooms": 1}}}
        )


@pytest.mark.parametrize("name", CLOSURE_TRAPS)
def test_closure_trap_is_deterministic(name):
    a = simulate_run(name, seed=4, duration=2.0, sensor__n_beams=91)
    b = simulate_run(name, seed=4, duration=2.0, sensor__n_beams=91)
    assert len(a.sequence) == 21 and a.sequence.metadata["scenario"] == name
    np.testing.assert_array_equal(a.sequence.ranges_matrix(), b.sequence.ranges_matrix())
    np.testing.assert_array_equal(a.sequence.odometry, b.sequence.odometry)
    np.testing.assert_array_equal(a.people_tracks, b.people_tracks)


@pytest.mark.parametrize("name", CLOSURE_TRAPS)
def test_closure_trap_revisits_with_drifting_odometry(name):
    res = _run(name)
    seq = res.sequence
    assert len(seq) == round(res.config.duration * 10) + 1
    assert np.isfinite(seq.ranges_matrix()).mean() > 0.3
    ref, odo = seq.reference, seq.odometry
    # some pose pair more than 20 s apart lies within 1 m: a revisit
    sub = ref[::5, :2]
    t = np.arange(len(ref))[::5] / 10.0
    close = np.hypot(*(sub[:, None, :] - sub[None, :, :]).transpose(2, 0, 1)) < 1.0
    assert np.any(close & (t[None, :] - t[:, None] > 20.0))
    # a full loop back to the start, where odometry has drifted: a closure is needed
    i = _first_return(ref)
    true = relative(ref[0], ref[i])
    drift = math.hypot(true[0] - odo[i, 0], true[1] - odo[i, 1])
    assert 0.1 < drift < 2.0


def test_twin_rooms_scans_are_aliased():
    res = _run("twin_rooms")
    info, ref = res.world.info, res.sequence.reference
    dx, xd, depth = info["twin_dx"], info["door_x"], info["room_depth"]
    assert 3.0 < dx < 5.0
    # poses in the first room, driving north away from its door
    heading = np.abs(wrap_angle(ref[:, 2] - math.pi / 2))
    sel = np.nonzero((np.abs(ref[:, 0] - xd) < 0.2) & (ref[:, 1] > 1.8) & (ref[:, 1] < depth - 2.0)
                     & (heading < 0.2))[0]  # fmt: skip
    assert sel.size
    pose = ref[sel[len(sel) // 2]]
    twin = pose + np.array([dx, 0.0, 0.0])
    # the robot also drives through the twin pose
    assert np.min(np.hypot(*(ref[:, :2] - twin[:2]).T)) < 0.3
    assert math.dist(pose[:2], twin[:2]) > 3.0
    a, b = _static_points(res, pose), _static_points(res, twin)
    assert _mean_nn(a, b - np.array([dx, 0.0])) < 0.05
    # without the shift the scans do not line up: the twin is another place
    assert _mean_nn(a, b) > 0.5


def test_twin_corridors_scans_are_aliased():
    res = _run("twin_corridors")
    info, ref = res.world.info, res.sequence.reference
    dy, period, length = info["twin_dy"], info["period"], info["length"]
    assert 3.0 < dy < 5.0
    # second lap: the south corridor driven westwards, mid-corridor
    west = np.abs(wrap_angle(ref[:, 2] - math.pi)) < 0.2
    sel = np.nonzero(west & (np.abs(ref[:, 1]) < 0.3) & (np.abs(ref[:, 0] - length / 2) < 0.5))[0]
    assert sel.size
    pose = ref[sel[len(sel) // 2]]
    twin = pose + np.array([0.0, dy, 0.0])
    # on the first lap the robot drove the twin pose (north corridor, westwards)
    near = np.hypot(*(ref[:, :2] - twin[:2]).T) < 0.3
    assert np.any(near & west)
    assert math.dist(pose[:2], twin[:2]) > 3.0
    a, b = _static_points(res, pose), _static_points(res, twin)
    assert _mean_nn(a, b - np.array([0.0, dy])) < 0.05
    assert _mean_nn(a, b) > 0.5
    # the corridor repeats itself: one period along, the local structure (6 m) is the same
    step = pose + np.array([period, 0.0, 0.0])
    a, b = _static_points(res, pose), _static_points(res, step) - np.array([period, 0.0])
    a = a[np.hypot(*(a - pose[:2]).T) < 6.0]
    b = b[np.hypot(*(b - pose[:2]).T) < 6.0]
    assert _mean_nn(a, b) < 0.05


def test_crowd_closure_fills_the_closing_point():
    res = _run("crowd_closure")
    ref, tracks = res.sequence.reference, res.people_tracks
    near = (np.hypot(*(tracks - ref[0, :2]).transpose(2, 0, 1)) < 3.0).sum(axis=1)
    assert near[:30].max() <= 1  # the first visit: the place is empty
    assert near[-50:].min() >= 15  # a standing crowd to the end
    # when the robot is back at its start, the crowd stands there and hides the walls
    i = _first_return(ref)
    assert near[i] >= 15
    moved = np.hypot(*(tracks[-1] - tracks[-50]).T)
    assert np.median(moved) < 0.3  # standing, not walking
    static = _static_points(res, ref[i])
    assert len(static)
    info = res.sequence.sensor
    w = res.world
    ang = info.angle_min + info.angle_increment * np.arange(info.n_beams) + ref[i, 2]
    expected = cast_rays(ref[i, :2].copy(), ang, w.segments, w.segment_material, w.circles,
                         w.circle_material, MaterialsConfig(), np.random.default_rng(0),
                         max_range=info.range_max * 1.5)  # fmt: skip
    occluded = np.mean(res.sequence.scans[i].ranges < expected - 0.3)
    assert occluded > 0.4
