from __future__ import annotations

import math

import numpy as np
import pytest

from scanguard.errors import ConfigError
from scanguard.geometry import transform_points
from scanguard.sim import (
    SCENARIOS,
    ScenarioConfig,
    build_world,
    cast_rays,
    load_scenario,
    measure,
    simulate,
    simulate_run,
)
from scanguard.sim.config import MaterialsConfig, OdometryConfig, SensorConfig, WorldConfig
from scanguard.sim.robot import odometry_increment
from tests.helpers import RPLIDAR, raycast, room_segments

Z8 = np.zeros(0, dtype=np.int8)


def _cast(segs, mats, circles=None, cmats=None, angles=None, materials=None, seed=0, **kw):
    angles = (
        RPLIDAR.angle_min + RPLIDAR.angle_increment * np.arange(1440) if angles is None else angles
    )
    segs = np.asarray(segs, dtype=float).reshape(-1, 4)
    circles = np.zeros((0, 3)) if circles is None else np.asarray(circles, dtype=float)
    cmats = np.zeros(len(circles), np.int8) if cmats is None else np.asarray(cmats, np.int8)
    return cast_rays(
        np.zeros(2), angles, segs, np.asarray(mats, np.int8), circles, cmats, materials,
        np.random.default_rng(seed), **kw,
    )  # fmt: skip


def test_wall_range_exact_at_known_distance_and_angle():
    angles = np.radians(np.array([-40.0, -10.0, 0.0, 25.0, 60.0]))
    r = _cast([(4.0, -20.0, 4.0, 20.0)], [0], angles=angles)
    np.testing.assert_allclose(r, 4.0 / np.cos(angles), rtol=0, atol=1e-12)
    # through the sensor model with zero noise the ranges survive unchanged (float32)
    cfg = SensorConfig(noise_std=0.0, noise_rel=0.0, dropout_prob=0.0)
    full = _cast([(4.0, -20.0, 4.0, 20.0)], [0])
    meas = measure(full, cfg, cfg.info(), np.random.default_rng(1))
    ang = RPLIDAR.angle_min + RPLIDAR.angle_increment * np.arange(1440)
    front = np.cos(ang) > 0.2
    np.testing.assert_allclose(meas[front], (4.0 / np.cos(ang[front])), rtol=1e-6)
    assert np.all(np.isinf(meas[np.cos(ang) < 0]))


def test_fast_caster_matches_brute_force_reference():
    segs = room_segments()
    rng = np.random.default_rng(5)
    for _ in range(20):
        pose = np.array([rng.uniform(-4, 4), rng.uniform(-2.5, 2.5), rng.uniform(-np.pi, np.pi)])
        ang = pose[2] + RPLIDAR.angle_min + RPLIDAR.angle_increment * np.arange(1440)
        ours = cast_rays(pose[:2], ang, segs, np.zeros(len(segs), np.int8), np.zeros((0, 3)), Z8)
        ref = raycast(segs, pose).astype(np.float64)
        np.testing.assert_allclose(ours, ref, rtol=1e-6)


def test_mirror_at_45_degrees_returns_mirrored_wall_distance():
    # beam along +x meets a 45° mirror at x=2, turns to +y and hits the wall y=3: 2 + 3 m
    mirror = (1.5, -0.5, 2.5, 0.5)
    wall = (-1.0, 3.0, 5.0, 3.0)
    m = MaterialsConfig(mirror={"specular_prob": 1.0, "dropout_prob": 0.0})
    r = _cast([mirror, wall], [2, 0], angles=np.array([0.0]), materials=m)
    assert r[0] == pytest.approx(5.0, abs=1e-9)
    # the phantom point lies behind the mirror, on the original beam
    assert r[0] > 2.0
    # the same geometry as a plain wall returns the pane itself
    assert _cast([mirror, wall], [0, 0], angles=np.array([0.0]))[0] == pytest.approx(2.0)


def test_glass_lets_beams_through_echoes_and_drops_at_configured_rates():
    segs = [(2.0, -50.0, 2.0, 50.0), (5.0, -50.0, 5.0, 50.0)]
    a = np.array([0.0])
    through = MaterialsConfig(glass={"reflect_prob": 0.0, "dropout_prob": 0.0})
    assert _cast(segs, [1, 0], angles=a, materials=through)[0] == pytest.approx(5.0)
    echo = MaterialsConfig(glass={"reflect_prob": 1.0, "dropout_prob": 0.0})
    assert _cast(segs, [1, 0], angles=a, materials=echo)[0] == pytest.approx(2.0)
    drop = MaterialsConfig(glass={"reflect_prob": 0.0, "dropout_prob": 1.0})
    assert np.isinf(_cast(segs, [1, 0], angles=a, materials=drop)[0])
    mix = MaterialsConfig(glass={"reflect_prob": 0.2, "dropout_prob": 0.1})
    angles = np.linspace(-1.0, 1.0, 20000)
    r = _cast(segs, [1, 0], angles=angles, materials=mix)
    pane = np.isclose(r, 2.0 / np.cos(angles))
    wall = np.isclose(r, 5.0 / np.cos(angles))
    assert pane.mean() == pytest.approx(0.2, abs=0.015)
    assert np.isinf(r).mean() == pytest.approx(0.1, abs=0.015)
    assert wall.mean() == pytest.approx(0.7, abs=0.015)


def test_beyond_max_range_is_inf():
    cfg = SensorConfig(noise_std=0.0, noise_rel=0.0, dropout_prob=0.0)
    info = cfg.info()
    ang = info.angle_min + info.angle_increment * np.arange(info.n_beams)
    far = _cast([(30.0, -1.0, 30.0, 1.0), (-24.0, -1.0, -24.0, 1.0)], [0, 0], angles=ang)
    meas = measure(far, cfg, info, np.random.default_rng(0))
    ahead = np.isfinite(far) & (np.cos(ang) > 0)
    behind = np.isfinite(far) & (np.cos(ang) < 0)
    assert ahead.sum() > 10 and behind.sum() > 10
    assert np.all(np.isinf(meas[ahead]))
    np.testing.assert_allclose(meas[behind], far[behind], rtol=1e-6)


def test_person_between_robot_and_wall_shortens_exactly_the_covered_beams():
    ang = RPLIDAR.angle_min + RPLIDAR.angle_increment * np.arange(1440)
    wall = [(6.0, -30.0, 6.0, 30.0)]
    person = np.array([[3.0, 0.0, 0.3]])
    r = _cast(wall, [0], circles=person)
    covered = (np.cos(ang) > 0) & (np.abs(3.0 * np.sin(ang)) < 0.3)
    expect_person = 3.0 * np.cos(ang) - np.sqrt(np.maximum(0.09 - 9.0 * np.sin(ang) ** 2, 0))
    np.testing.assert_allclose(r[covered], expect_person[covered], atol=1e-9)
    front = (np.abs(6.0 * np.tan(ang)) < 30.0) & (np.cos(ang) > 0) & ~covered
    np.testing.assert_allclose(r[front], 6.0 / np.cos(ang[front]), atol=1e-9)
    # 0.3 m at 3 m covers 2*asin(0.1) = 11.48 deg = 45 or 46 beams of 0.25 deg
    assert covered.sum() in (45, 46)


def test_odometry_error_statistics_match_configured_noise():
    cfg = OdometryConfig(
        rot_per_rot=0.05, rot_per_trans=0.02, trans_per_trans=0.03, trans_per_rot=0.01,
        scale_error=0.01, turn_error=-0.02,
    )  # fmt: skip
    rng = np.random.default_rng(0)
    n = 20000
    straight = np.array([odometry_increment(np.array([0.1, 0.0, 0.0]), cfg, rng) for _ in range(n)])
    trans = np.hypot(straight[:, 0], straight[:, 1])
    assert trans.mean() == pytest.approx(0.1 * 1.01, rel=2e-3)
    assert trans.std() == pytest.approx(0.03 * 0.1, rel=0.03)
    # heading noise: rot1 and rot2 each get rot_per_trans * trans
    assert straight[:, 2].std() == pytest.approx(math.sqrt(2) * 0.02 * 0.1, rel=0.03)
    turn = np.array([odometry_increment(np.array([0.0, 0.0, 0.3]), cfg, rng) for _ in range(n)])
    assert turn[:, 2].mean() == pytest.approx(0.3 * 0.98, rel=2e-3)
    assert turn[:, 2].std() == pytest.approx(0.05 * 0.3, rel=0.03)
    assert np.hypot(turn[:, 0], turn[:, 1]).mean() == pytest.approx(
        0.01 * 0.3 * math.sqrt(2 / math.pi), rel=0.05
    )


def test_same_seed_gives_identical_sequences_and_other_seeds_differ():
    a = simulate("lobby", seed=7, duration=1.0)
    b = simulate("lobby", seed=7, duration=1.0)
    c = simulate("lobby", seed=8, duration=1.0)
    assert len(a) == len(b) == 11
    np.testing.assert_array_equal(a.ranges_matrix(), b.ranges_matrix())
    np.testing.assert_array_equal(a.reference, b.reference)
    np.testing.assert_array_equal(a.odometry, b.odometry)
    np.testing.assert_array_equal(a.stamps, b.stamps)
    assert not np.array_equal(a.ranges_matrix(), c.ranges_matrix())


def test_sequence_contract_and_odometry_drift():
    seq = simulate("lobby", seed=1, duration=6.0, people__count=10)
    assert seq.reference_kind == "ground_truth"
    assert seq.metadata["scenario"] == "lobby" and seq.metadata["seed"] == 1
    assert seq.sensor.n_beams == 1440 and seq.rate_hz == pytest.approx(10.0)
    np.testing.assert_array_equal(seq.odometry[0], np.zeros(3))
    # odometry increments are close to, but not exactly, the true ones
    from scanguard.geometry import relative

    rel_true = relative(seq.reference[:-1], seq.reference[1:])
    rel_odo = relative(seq.odometry[:-1], seq.odometry[1:])
    err = np.abs(rel_true - rel_odo)
    moving = np.hypot(rel_true[:, 0], rel_true[:, 1]) > 0.02
    assert moving.sum() > 5
    assert 0 < err[moving, 0].max() < 0.05


def test_stride_keeps_every_kth_scan_of_the_same_run():
    full = simulate("corridor", seed=2, duration=2.0, people__count=5)
    half = simulate("corridor", seed=2, duration=2.0, people__count=5, stride=2)
    assert len(half) == 11 and len(full) == 21
    np.testing.assert_array_equal(half.reference, full.reference[::2])
    np.testing.assert_allclose(np.diff(half.stamps), 0.2, atol=1e-6)
    assert half.rate_hz == pytest.approx(5.0)


def test_robot_and_people_never_collide_with_walls_or_each_other():
    res = simulate_run("lobby", seed=3, duration=15.0)
    world = res.world
    r_robot = res.config.robot.radius
    assert np.all(world.grid().clearance_at(res.robot_path[:, :2]) >= r_robot)
    d = np.hypot(*(res.people_tracks - res.robot_path[:, None, :2]).transpose(2, 0, 1))
    assert d.min() > r_robot + 0.15
    clear = world.grid().clearance_at(res.people_tracks.reshape(-1, 2))
    assert clear.min() > 0.1
    speed = np.hypot(*np.diff(res.people_tracks, axis=0).transpose(2, 0, 1)) * 10.0
    assert np.percentile(speed[speed > 0.2], 95) <= 2.0
    path = np.hypot(*np.diff(res.robot_path[:, :2], axis=0).T)
    assert path.max() * 10 <= 1.2 + 1e-9  # R1 speed limit
    assert path.sum() > 3.0


def test_corridor_scans_are_nearly_identical_along_the_axis():
    from scipy.spatial import cKDTree

    cfg = load_scenario("corridor")
    world = build_world(cfg.world, np.random.default_rng([4, 0]), "corridor")
    info = cfg.sensor.info()
    ang = info.angle_min + info.angle_increment * np.arange(info.n_beams)
    x, y = world.start[0], 0.0

    def pts(px: float, py: float) -> np.ndarray:
        r = cast_rays(np.array([px, py]), ang, world.segments, world.segment_material,
                      world.circles, world.circle_material)  # fmt: skip
        ok = np.isfinite(r) & (r < info.range_max)
        return np.column_stack([r[ok] * np.cos(ang[ok]), r[ok] * np.sin(ang[ok])])

    ref = cKDTree(pts(x, y))
    along = np.median(ref.query(pts(x + 0.3, y))[0])
    across = np.median(ref.query(pts(x, y + 0.3))[0])
    assert along < 0.01  # the shifted scan lies on the same two walls
    assert across > 0.2


def test_hall_has_a_sizeable_fraction_of_inf_beams():
    seq = simulate("hall", seed=0, duration=2.0)
    assert np.isinf(seq.ranges_matrix()).mean() > 0.2


def test_glass_world_has_phantom_points_behind_mirrors():
    res = simulate_run("glass", seed=1, duration=3.0, people__count=0)
    world, seq = res.world, res.sequence
    phantom = 0
    for scan, pose in zip(seq.scans, seq.reference, strict=True):
        p = transform_points(pose, scan.points(np.float64))
        segs = world.segments
        # distance to the nearest real surface: phantoms float where nothing is
        a, e = segs[None, :, :2], segs[None, :, 2:] - segs[None, :, :2]
        t = np.clip(((p[:, None] - a) * e).sum(-1) / (e * e).sum(-1), 0, 1)
        d = np.hypot(*(p[:, None] - a - t[..., None] * e).transpose(2, 0, 1)).min(1)
        if len(world.circles):
            dc = np.hypot(*(p[:, None] - world.circles[None, :, :2]).transpose(2, 0, 1))
            d = np.minimum(d, (dc - world.circles[None, :, 2]).min(1))
        phantom += int((d > 0.3).sum())
    assert phantom > 50


def test_all_builtin_scenarios_run_and_office_uses_the_pr2_laser():
    for name in SCENARIOS:
        seq = simulate(name, seed=0, duration=0.5)
        assert len(seq) == 6
        assert seq.metadata["scenario"] == name
    office = simulate("office", seed=0, duration=0.3)
    assert office.sensor.n_beams == 1040
    assert office.sensor.fov_deg == pytest.approx(270.0)


def test_layout_varies_with_the_seed():
    cfg = load_scenario("lobby")
    w1 = build_world(cfg.world, np.random.default_rng([1, 0]), "lobby")
    w2 = build_world(cfg.world, np.random.default_rng([2, 0]), "lobby")
    assert w1.segments.shape != w2.segments.shape or not np.allclose(w1.segments, w2.segments)


def test_custom_yaml_world_and_bad_overrides(tmp_path):
    text = """
name: box
world:
  walls:
    - {points: [[-3, -2], [3, -2], [3, 2], [-3, 2]], closed: true}
    - {points: [[1, -1], [1.5, -0.5]], material: mirror}
  circles: [{center: [-1.5, 1.0], radius: 0.3}]
  start: [0, 0, 0]
people: {count: 2}
"""
    path = tmp_path / "box.yaml"
    path.write_text(text)
    seq = simulate(str(path), seed=0, duration=0.5, sensor__noise_std=0.0)
    assert len(seq) == 6 and np.isfinite(seq.ranges_matrix()).mean() > 0.9
    with pytest.raises(ConfigError, match="people"):
        simulate("lobby", seed=0, duration=1.0, people__colour="red")
    with pytest.raises(ConfigError, match="unknown scenario"):
        simulate("moon", seed=0, duration=1.0)
    with pytest.raises(ConfigError, match="not enclosed"):
        open_world = WorldConfig(walls=[{"points": [[0, -1], [5, -1]]}], start=(2.0, -0.5, 0.0))
        build_world(open_world, np.random.default_rng(0))


def test_same_seed_gives_identical_bags_that_read_back(tmp_path):
    io = pytest.importorskip("scanguard.io")
    # same file name in two folders: the bag records its own name
    a = io.write_sequence(simulate("glass", seed=5, duration=1.0), tmp_path / "a" / "s.mcap")
    b = io.write_sequence(simulate("glass", seed=5, duration=1.0), tmp_path / "b" / "s.mcap")
    assert a.read_bytes() == b.read_bytes()
    back = io.read_sequence(a)
    ref = simulate("glass", seed=5, duration=1.0)
    np.testing.assert_array_equal(back.ranges_matrix(), ref.ranges_matrix())
    np.testing.assert_allclose(back.reference, ref.reference, atol=1e-6)
    np.testing.assert_allclose(back.odometry, ref.odometry, atol=1e-6)


def test_cli_simulate_writes_bag_config_and_preview(tmp_path):
    from typer.testing import CliRunner

    from scanguard.cli import app

    out = tmp_path / "c.mcap"
    png = tmp_path / "c.png"
    res = CliRunner().invoke(
        app,
        ["simulate", "--scenario", "corridor", "--seed", "3", "--duration", "1", "-o", str(out),
         "--preview", str(png), "--stride", "2", "--set", "people.count=3"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert out.stat().st_size > 0 and png.read_bytes()[:4] == b"\x89PNG"
    saved = ScenarioConfig.from_yaml(tmp_path / "c.scenario.yaml")
    assert saved.stride == 2 and saved.people.count == 3 and saved.name == "corridor"
    bad = CliRunner().invoke(app, ["simulate", "--scenario", "moon", "-o", str(out)])
    assert bad.exit_code == 1 and "unknown scenario" in bad.output


# --- GMapping trap scenarios and the optional people behaviours -----------------------------

# sha256 of ranges (float32), reference and odometry (float64) of simulate("lobby", seed=3,
# duration=2.0), recorded before the optional behaviours were added: they must not change it
LOBBY_SEED3_SHA256 = "77d10c4cfdba634a4317bac9f157740087f970ae55277971131f89638f664198"


def test_existing_scenario_output_is_unchanged_golden_checksum():
    import hashlib

    seq = simulate("lobby", seed=3, duration=2.0)
    assert len(seq) == 21
    h = hashlib.sha256()
    for a in (seq.ranges_matrix(), seq.reference, seq.odometry):
        h.update(np.ascontiguousarray(a).tobytes())
    assert h.hexdigest() == LOBBY_SEED3_SHA256


def test_gmapping_traps_are_listed_loops_with_a_default_duration():
    from scanguard.sim import GMAPPING_TRAPS

    assert GMAPPING_TRAPS == (
        "crowd_stop",
        "crowd_follow",
        "long_corridor",
        "glass_hall",
        "mixed_loop",
    )
    assert not set(GMAPPING_TRAPS) & set(SCENARIOS)
    for name in GMAPPING_TRAPS:
        cfg = load_scenario(name)
        assert cfg.name == name and cfg.duration is not None and cfg.duration >= 120
        assert cfg.robot.mode == "route"
        rate = 1.0 / cfg.scan_period()
        assert 10.0 <= rate <= 15.0
        info = cfg.sensor.info()
        assert info.fov_deg == pytest.approx(270.0) and 720 <= info.n_beams <= 1081
        world = build_world(cfg.world, np.random.default_rng([5, 0]), name)
        # the route closes the loop: its last waypoint is the start
        np.testing.assert_allclose(world.route[-1], world.start[:2])
        assert len(world.route) >= 2
    # the paper scenarios have no default duration
    with pytest.raises(ConfigError, match="duration"):
        simulate("lobby", seed=0)


@pytest.mark.parametrize(
    "name", ["crowd_stop", "crowd_follow", "long_corridor", "glass_hall", "mixed_loop"]
)
def test_gmapping_trap_is_deterministic(name):
    a = simulate_run(name, seed=4, duration=3.0)
    b = simulate_run(name, seed=4, duration=3.0)
    assert len(a.sequence) == 31 and a.sequence.metadata["scenario"] == name
    np.testing.assert_array_equal(a.sequence.ranges_matrix(), b.sequence.ranges_matrix())
    np.testing.assert_array_equal(a.sequence.reference, b.sequence.reference)
    np.testing.assert_array_equal(a.sequence.odometry, b.sequence.odometry)
    np.testing.assert_array_equal(a.people_tracks, b.people_tracks)
    np.testing.assert_array_equal(a.people_paused, b.people_paused)
    assert np.isfinite(a.sequence.ranges_matrix()).mean() > 0.3
    # the robot moves off along its route
    assert np.hypot(*(a.robot_path[-1, :2] - a.robot_path[0, :2])) > 0.5


def _box_world(half: float = 6.0):
    cfg = WorldConfig(
        walls=[
            {"points": [[-half, -half], [half, -half], [half, half], [-half, half]], "closed": True}
        ],
        start=(0.0, 0.0, 0.0),
    )
    return build_world(cfg, np.random.default_rng(0), "box")


def test_pausing_groups_stop_together_then_walk_on():
    from scanguard.sim.config import PeopleConfig
    from scanguard.sim.people import Crowd

    world = _box_world()
    walk = PeopleConfig(
        count=6, standing_fraction=0.0, group_fraction=1.0, group_size=(3, 3), approach_fraction=0.0
    )
    rng = np.random.default_rng(1)
    far = np.array([50.0, 50.0])  # the robot is out of the way
    crowd = Crowd.spawn(walk, world, rng, far, 0.3)
    assert set(crowd.group.tolist()) == {0, 1}
    # two groups of three that walk together (spawning scatters them)
    for g, cx in ((0, -2.0), (1, 2.0)):
        crowd.pos[crowd.group == g] = np.array([[cx, -0.6], [cx + 0.6, 0.0], [cx, 0.6]])
    for _ in range(60):  # 3 s of walking
        crowd.step(0.05, world, rng, far, 0.3)
    assert not crowd.paused.any()
    assert np.hypot(*crowd.vel.T).mean() > 0.3
    # now every walking group stops at once (a huge stop rate) for exactly 6 s
    crowd.config = walk.model_copy(update={"pause_rate": 100.0, "pause_duration": (6.0, 6.0)})
    crowd.step(0.05, world, rng, far, 0.3)
    assert crowd.paused.all()
    for g in (0, 1):  # members of a group share the stop
        assert np.ptp(crowd.pause_left[crowd.group == g]) == 0.0
    before = crowd.pos.copy()
    for _ in range(20):  # within 1 s they halt (a stopped walker shuffles at <= 0.3 m/s)
        crowd.step(0.05, world, rng, far, 0.3)
    assert np.hypot(*(crowd.pos - before).T).max() < 0.45
    for _ in range(40):  # 2 s to close up the group
        crowd.step(0.05, world, rng, far, 0.3)
    before = crowd.pos.copy()
    for _ in range(30):  # 1.5 s of standing: (almost) no motion
        crowd.step(0.05, world, rng, far, 0.3)
    assert crowd.paused.all()
    moved = np.hypot(*(crowd.pos - before).T)
    assert np.median(moved) < 0.1 and moved.max() < 0.2
    # after the stop they walk on (at this huge rate they stop again right after)
    walked = False
    for _ in range(40):
        crowd.step(0.05, world, rng, far, 0.3)
        walked |= bool((~crowd.paused).any())
    assert walked


def test_crowd_stop_people_stand_for_a_while_while_others_walk():
    res = simulate_run("crowd_stop", seed=2, duration=30.0)
    paused = res.people_paused
    tracks = res.people_tracks
    speed = np.hypot(*np.diff(tracks, axis=0).transpose(2, 0, 1)) * 10.0  # (M-1, N) m/s
    assert paused.any(axis=0).sum() >= 10  # many people stop at some point
    frac = paused.mean(axis=1)
    assert 0.1 < frac[100:].mean() < 0.9  # some stand while the others walk
    stood = 0
    for k in range(paused.shape[1]):
        run = 0
        for i in range(1, paused.shape[0]):
            run = run + 1 if paused[i, k] and paused[i - 1, k] else 0
            if run == 30:  # 3 s stopped: the walker stands still then ...
                seg = speed[i - 30 : i, k]
                walked = speed[~paused[1:, k], k]
                # ... after (or before) walking at a normal pace
                if np.median(seg) < 0.1 and walked.size and np.percentile(walked, 90) > 0.5:
                    stood += 1
                    # and meanwhile others walk
                    assert (speed[i - 30 : i] > 0.4).sum(axis=1).mean() >= 3
                break
    assert stood >= 5


def test_crowd_follow_followers_keep_pace_beside_the_robot():
    res = simulate_run("crowd_follow", seed=1, duration=25.0)
    fol = res.people_followers
    assert fol.sum() == 8
    path = res.robot_path
    step = np.diff(path, axis=0)
    v = np.hypot(step[:, 0], step[:, 1]) * 10.0
    w = np.abs(np.angle(np.exp(1j * step[:, 2]))) * 10.0
    straight = (v > 0.6) & (w < 0.05)
    straight[:30] = False  # let them settle for 3 s
    assert straight.sum() > 100
    vel = np.diff(res.people_tracks[:, fol], axis=0)[straight] * 10.0  # (S, F, 2)
    heading = path[:-1, 2][straight]
    mean_v = vel.mean(axis=1)
    err = np.degrees(
        np.abs(np.angle(np.exp(1j * (np.arctan2(mean_v[:, 1], mean_v[:, 0]) - heading))))
    )
    assert np.median(err) < 10.0
    assert np.mean(err < 30.0) > 0.9
    ratio = np.hypot(mean_v[:, 0], mean_v[:, 1]).mean() / v[straight].mean()
    assert 0.8 < ratio < 1.3
    # and they stay a few metres beside it
    rel = res.people_tracks[1:][straight][:, fol] - path[1:][straight][:, None, :2]
    dist = np.hypot(rel[..., 0], rel[..., 1])
    assert 0.8 < np.median(dist) < 3.5
    # non-followers walk anywhere
    others = ~fol & (res.people_kinds != 2)
    assert others.sum() >= 5


def test_long_corridor_width_and_ends_beyond_range():
    res = simulate_run("long_corridor", seed=3, duration=40.0, people__count=0)
    cfg, seq = res.config, res.sequence
    assert cfg.sensor.info().range_max == pytest.approx(10.0)
    length = res.world.info["length"]
    assert 60.0 <= length <= 70.0
    widths, axial_inf = [], []
    ang = seq.sensor.angle_min + seq.sensor.angle_increment * np.arange(seq.sensor.n_beams)
    for scan, pose in zip(seq.scans, seq.reference, strict=True):
        if abs(pose[0]) > 8.0 or abs(np.sin(pose[2])) > 0.05:
            continue  # the middle of the corridor, driving along it
        p = transform_points(pose, scan.points(np.float64))
        near = np.abs(p[:, 0] - pose[0]) < 3.0
        up, down = p[near & (p[:, 1] > pose[1]), 1], p[near & (p[:, 1] < pose[1]), 1]
        widths.append(np.median(up) - np.median(down))
        axial_inf.append(np.isinf(scan.ranges[np.abs(ang) < np.radians(5)]).mean())
    assert len(widths) > 20
    assert np.median(widths) == pytest.approx(2.5, abs=0.03)
    # both ends are > 10 m away: nothing returns along the corridor axis
    assert np.mean(axial_inf) > 0.95


def test_wheel_slip_adds_forward_motion_inside_its_windows_only():
    """Slip (`OdometryConfig.slip_every`) changes the wheels by slip_speed * dt, nothing else."""
    from scanguard.geometry import relative

    plain = simulate("lobby", seed=3, duration=6.0)
    slip = simulate(
        "lobby", seed=3, duration=6.0, odometry__slip_every=2.0, odometry__slip_duration=1.0,
        odometry__slip_speed=0.5,
    )  # fmt: skip
    assert "wheel_slip" not in plain.metadata
    windows = slip.metadata["wheel_slip"]
    assert 1 <= len(windows) <= 4
    assert all(b - a == pytest.approx(1.0) or b >= plain.stamps[-1] - 1e-3 for a, b in windows)
    # the world, the people and the laser do not see the slip: only the wheels do
    np.testing.assert_array_equal(plain.ranges_matrix(), slip.ranges_matrix())
    np.testing.assert_array_equal(plain.reference, slip.reference)
    period = 1.0 / plain.metadata["scan_rate_hz"]  # the stamps are rounded, the rate is not
    n_slipping = 0
    for k in range(1, len(plain)):
        d = relative(slip.odometry[k - 1], slip.odometry[k]) - relative(
            plain.odometry[k - 1], plain.odometry[k]
        )
        t = plain.stamps[k]
        inside = any(a < t <= b for a, b in windows)
        n_slipping += inside
        expected = [0.5 * period if inside else 0.0, 0.0, 0.0]
        np.testing.assert_allclose(d, expected, atol=1e-9)
    assert n_slipping >= 9  # at least one whole 1-s event at 10 Hz


def test_office_slip_scene_slips_about_every_twenty_seconds():
    cfg = load_scenario("office_slip")
    assert cfg.odometry.slip_every == 20.0 and cfg.odometry.slip_speed == 0.5
    assert cfg.sensor.model == load_scenario("office").sensor.model
