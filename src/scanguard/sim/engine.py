"""The simulation loop: world + people + robot + laser → `ScanSequence` with exact ground truth."""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import ConfigError
from scanguard.geometry import compose, relative
from scanguard.logging_utils import progress as report_progress
from scanguard.safeload import parse_yaml
from scanguard.scan import LaserScan, ScanSequence, SensorInfo
from scanguard.sim.config import ScenarioConfig
from scanguard.sim.limits import RunPlan, check_duration, check_seed, plan_run
from scanguard.sim.people import Crowd
from scanguard.sim.raycast import cast_rays, measure
from scanguard.sim.robot import Robot, odometry_increment, slip_increment, slip_windows
from scanguard.sim.world import World
from scanguard.sim.worldgen import build_world

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Built-in scenario names of the paper's Environments 1-5 (YAML files shipped in
#: ``scanguard/sim/scenarios``).
SCENARIOS: tuple[str, ...] = ("lobby", "corridor", "glass", "hall", "office")

#: Built-in scenarios where a particle-filter SLAM back end (GMapping) itself fails: crowds
#: that stop and occlude the walls, walkers that move with the robot, a long featureless
#: corridor beyond the sensor range, glass and mirrors, and a generic building loop. Each is a
#: loop (or out-and-back) route driven for its default ``duration`` with drifting odometry.
GMAPPING_TRAPS: tuple[str, ...] = (
    "crowd_stop",
    "crowd_follow",
    "long_corridor",
    "glass_hall",
    "mixed_loop",
)

#: Built-in scenarios where a pose-graph back end that accepts loop closures without judging
#: them folds its map: identical rooms side by side (`twin_rooms`), two identical periodic
#: corridors (`twin_corridors`), and a loop whose closing point is filled by a standing crowd
#: that was absent on the first visit (`crowd_closure`). Each is a loop driven more than once
#: for its default ``duration`` with drifting odometry.
CLOSURE_TRAPS: tuple[str, ...] = ("twin_rooms", "twin_corridors", "crowd_closure")

#: Built-in scenarios where the judge decides which motion estimate to trust: the office of
#: Environment 5 whose wheels slip now and then (`office_slip`; `scanguard demo` runs it).
GUARD_SCENES: tuple[str, ...] = ("office_slip",)

#: Stamp of the first scan (s since the epoch): ROS tools dislike time zero.
START_STAMP = 1_700_000_000.0

# independent random streams per component, so that e.g. changing the sensor noise does not
# change the floor plan or the walkers
_WORLD, _PEOPLE, _ROBOT, _SENSOR, _MATERIAL, _ODOM, _SLIP = range(7)


def load_scenario(scenario: str | Path | ScenarioConfig) -> ScenarioConfig:
    """A scenario by built-in name, YAML path, or as given.

    Raises:
        ConfigError: Unknown name or invalid file (the message lists the built-in names).
    """
    if isinstance(scenario, ScenarioConfig):
        return scenario
    s = str(scenario)
    if s in SCENARIOS + GMAPPING_TRAPS + CLOSURE_TRAPS + GUARD_SCENES:
        text = resources.files("scanguard.sim").joinpath("scenarios", f"{s}.yaml")
        with resources.as_file(text) as p:
            return ScenarioConfig.from_yaml(p)
    p = Path(s)
    if p.suffix in {".yaml", ".yml"}:
        return ScenarioConfig.from_yaml(p)
    raise ConfigError(
        f"unknown scenario {s!r}: use one of "
        f"{', '.join(SCENARIOS + GMAPPING_TRAPS + CLOSURE_TRAPS + GUARD_SCENES)} or a path to a "
        "YAML file"
    )


def _merge(base: dict[str, Any], over: dict[str, Any], where: str) -> None:
    for key, val in over.items():
        if isinstance(val, dict) and isinstance(base.get(key), dict):
            _merge(base[key], val, f"{where}{key}.")
        else:
            base[key] = val


def apply_overrides(config: ScenarioConfig, **overrides: Any) -> ScenarioConfig:
    """A copy of ``config`` with overrides applied.

    Keys are top-level fields (``stride=2``, ``people={"count": 10}``) or nested paths
    written with double underscores (``people__count=10``, ``sensor__noise_std=0``).

    Raises:
        ConfigError: An override names an unknown field or has an invalid value.
    """
    if not overrides:
        return config
    data = copy.deepcopy(config.model_dump(mode="python"))
    for key, val in overrides.items():
        parts = key.split("__")
        nested: dict[str, Any] = {parts[-1]: val}
        for p in reversed(parts[:-1]):
            nested = {p: nested}
        _merge(data, nested, "")
    return ScenarioConfig.from_dict(data, source=f"scenario {config.name!r} overrides")


class ScanSink(Protocol):
    """Receives the scans of a run as they are simulated (e.g. a bag writer).

    `begin` is called once, before the first scan, with a sequence that has no scans but the
    run's name, sensor, laser offset, reference kind and metadata; then `add` for every kept
    scan, in order.
    """

    def begin(self, header: ScanSequence) -> None:
        """Start the output."""

    def add(self, scan: LaserScan, reference: FloatArray, odometry: FloatArray) -> None:
        """Take one scan with its ground-truth and odometry poses."""


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """Overrides from ``--set key=value`` strings (dotted keys, YAML values).

    ``["people.count=10", "sensor={noise_std: 0}"]`` gives ``{"people__count": 10,
    "sensor": {"noise_std": 0}}`` for `apply_overrides`.

    Raises:
        ConfigError: An item without ``=`` or a key, or a value that is not valid YAML (one
            line naming the item).
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected key=value, e.g. people.count=20")
        try:  # bounded like every config: an alias bomb or deep nesting is a one-line error
            parsed = parse_yaml(value)
        except ValueError as exc:
            raise ConfigError(f"invalid YAML in --set {item[:80]!r}: {exc}") from None
        out[key.strip().replace(".", "__")] = parsed
    return out


@dataclass
class SimulationResult:
    """Everything a run produced (the sequence plus what the preview draws).

    Attributes:
        sequence: Scans, drifting odometry, exact ground truth. When the scans were only
            streamed to a sink (``keep_scans=False``) it holds no scans and no poses, only
            the name, sensor, laser offset and metadata.
        world: The static world.
        config: The resolved scenario.
        robot_path: Ground-truth robot poses at every simulated scan ``(M, 3)``.
        people_tracks: Agent positions at every simulated scan ``(M, N, 2)``.
        people_kinds: Agent kind codes ``(N,)`` (0 legs, 1 body, 2 cart).
        people_paused: Agents stopped by a pause at every simulated scan ``(M, N)``
            (all False unless ``people.pause_prob``/``pause_rate`` are set).
        people_followers: Agents that walk alongside the robot ``(N,)``.
        n_kept: Number of scans of the run (also when they were not kept).
        inf_fraction: Fraction of the beams of those scans that returned nothing (inf).
        middle_scan: Scan ``n_kept // 2`` (the one the preview draws).
    """

    sequence: ScanSequence
    world: World
    config: ScenarioConfig
    robot_path: FloatArray
    people_tracks: FloatArray
    people_kinds: NDArray[np.int8]
    people_paused: NDArray[np.bool_] = field(default_factory=lambda: np.zeros((0, 0), bool))
    people_followers: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    n_kept: int = 0
    inf_fraction: float = 0.0
    middle_scan: LaserScan | None = None


def plan_simulation(
    scenario: str | Path | ScenarioConfig,
    *,
    duration: float | None = None,
    keep_scans: bool = True,
    **overrides: Any,
) -> tuple[ScenarioConfig, float, RunPlan]:
    """Resolve a scenario and size its run, without simulating anything.

    `simulate_run` does this first; call it yourself to check a run (and e.g. its output's
    disk space, `RunPlan.bag_bytes`) before opening outputs.

    Args:
        scenario: Built-in name, YAML path or config.
        duration: Simulated seconds (finite, > 0); None = the scenario's ``duration``.
        keep_scans: Whether the scans will be kept in memory.
        **overrides: Config overrides (see `apply_overrides`).

    Returns:
        The resolved config, the duration and the run's plan.

    Raises:
        ConfigError: Invalid scenario, overrides or duration, or a run over the limits of
            `scanguard.sim.limits`.
    """
    cfg = apply_overrides(load_scenario(scenario), **overrides)
    if duration is None:
        if cfg.duration is None:
            raise ConfigError(f"scenario {cfg.name!r} has no default duration: pass duration=")
        duration = cfg.duration
    value = check_duration(duration)
    return cfg, value, plan_run(cfg, value, keep_scans=keep_scans)


def simulate_run(
    scenario: str | Path | ScenarioConfig,
    *,
    seed: int,
    duration: float | None = None,
    progress: bool = False,
    sink: ScanSink | None = None,
    keep_scans: bool = True,
    **overrides: Any,
) -> SimulationResult:
    """Run a scenario and keep the world and tracks (see `simulate`).

    The seed, the duration and the run's size (memory, scans, physics steps, navigation
    grid; `scanguard.sim.limits`) are checked before anything large is allocated.

    Args:
        scenario: Built-in name, YAML path or config.
        seed: Seed of everything random (floor-plan variant, people, noise), >= 0.
        duration: Simulated seconds (finite, > 0); None = the scenario's ``duration``.
        progress: Show progress: a bar when stderr is a terminal, else a log line every
            10 % of the scans.
        sink: Receives every kept scan as soon as it is simulated (e.g. a streaming bag
            writer, `scanguard.sim.output.BagStreamWriter`).
        keep_scans: Keep the scans in ``result.sequence``; False with a ``sink`` streams them
            in constant memory (the sequence then holds no scans).
        **overrides: Config overrides (see `apply_overrides`).

    Returns:
        The result.

    Raises:
        ConfigError: Invalid scenario, overrides, seed or duration, or a run too large.
    """
    seed = check_seed(seed)
    cfg, duration, plan = plan_simulation(
        scenario, duration=duration, keep_scans=keep_scans, **overrides
    )
    streams = [np.random.default_rng([int(seed), k]) for k in range(7)]
    info = cfg.sensor.info()
    period = plan.period
    dt = period / plan.n_sub
    world, robot, crowd = _setup(cfg, plan, streams)
    offset = np.asarray(cfg.robot.laser_offset, dtype=np.float64)
    beam_angles = info.angle_min + info.angle_increment * np.arange(info.n_beams)
    n_scans = plan.n_scans
    rate = 1.0 / (period * cfg.stride)
    out_info, metadata = _header(cfg, info, rate, seed, duration, crowd.n)
    slips = slip_windows(cfg.odometry, duration, streams[_SLIP])
    if slips:
        metadata["wheel_slip"] = [[START_STAMP + a, START_STAMP + b] for a, b in slips]
    name = f"{cfg.name}-seed{seed}"
    if sink is not None:
        sink.begin(_sequence(name, [], out_info, offset, dict(metadata)))
    rec = _Recorder(sink, keep_scans, plan.n_kept // 2, n_scans, crowd.n)
    odo = np.zeros(3)  # the odometry frame starts where the robot is switched on
    prev_true = robot.pose.copy()
    with report_progress(
        n_scans, f"simulating {cfg.name} (seed {seed})", logger=log, enabled=progress
    ) as advance:
        for i in range(n_scans):
            if i > 0:
                _physics(cfg, world, robot, crowd, streams[_PEOPLE], dt, plan.n_sub)
                delta = relative(prev_true, robot.pose)
                inc = odometry_increment(delta, cfg.odometry, streams[_ODOM])
                if slips:
                    inc += slip_increment(i * period, slips, cfg.odometry.slip_speed, period)
                odo = compose(odo, inc)
                prev_true = robot.pose.copy()
            rec.state(i, robot.pose, crowd)
            # the materials stream is drawn every scan (also skipped ones) for determinism
            laser = compose(robot.pose, offset)
            ranges = _ranges(cfg, info, world, crowd, laser, beam_angles, streams)
            if i % cfg.stride == 0:
                rec.keep(LaserScan.from_sensor(info, START_STAMP + i * period, ranges), robot, odo)
            advance(1)
    seq = _sequence(name, rec.scans, out_info, offset, metadata, *rec.poses())
    log.info("simulated %s seed %d: %d scans, %d agents", cfg.name, seed, rec.n_kept, crowd.n)
    return rec.result(seq, world, cfg, crowd, info.n_beams)


def _header(
    cfg: ScenarioConfig, info: SensorInfo, rate: float, seed: int, duration: float, n_people: int
) -> tuple[SensorInfo, dict[str, Any]]:
    """The output sensor (the scan rate after the stride) and the run's metadata."""
    out_info = SensorInfo(
        name=info.name,
        n_beams=info.n_beams,
        angle_min=info.angle_min,
        angle_increment=info.angle_increment,
        range_min=info.range_min,
        range_max=info.range_max,
        rate_hz=rate,
    )
    metadata = {
        "scenario": cfg.name,
        "seed": int(seed),
        "duration": float(duration),
        "environment": cfg.environment,
        "sensor_model": cfg.sensor.model,
        "n_people": int(n_people),
        "scan_rate_hz": rate,
        "stride": cfg.stride,
        "source": "scanguard.sim",
    }
    return out_info, metadata


def _sequence(
    name: str,
    scans: list[LaserScan],
    sensor: SensorInfo,
    offset: FloatArray,
    metadata: dict[str, Any],
    odometry: FloatArray | None = None,
    reference: FloatArray | None = None,
) -> ScanSequence:
    """The run's sequence: its sensor, laser offset and metadata, and the kept scans."""
    return ScanSequence(
        name=name,
        scans=scans,
        sensor=sensor,
        odometry=odometry,
        reference=reference,
        reference_kind="ground_truth",
        laser_offset=offset,
        metadata=metadata,
    )


def _setup(
    cfg: ScenarioConfig, plan: RunPlan, streams: list[np.random.Generator]
) -> tuple[World, Robot, Crowd]:
    """The world, the robot at its start and the crowd, each from its own random stream."""
    world = build_world(
        cfg.world,
        streams[_WORLD],
        cfg.name,
        clearance=cfg.robot.radius + cfg.robot.clearance,
        other_bytes=plan.memory_bytes,
    )
    robot = Robot(cfg.robot, world, streams[_ROBOT], world.start)
    crowd = Crowd.spawn(
        cfg.people,
        world,
        streams[_PEOPLE],
        robot.xy,
        cfg.robot.radius,
        robot_heading=float(robot.pose[2]),
        route=robot.route,
    )
    return world, robot, crowd


def _physics(
    cfg: ScenarioConfig,
    world: World,
    robot: Robot,
    crowd: Crowd,
    rng: np.random.Generator,
    dt: float,
    n_sub: int,
) -> None:
    """Advance the robot and the people by one scan period (``n_sub`` steps of ``dt``)."""
    for _ in range(n_sub):
        robot.step(dt, crowd.pos, crowd.radius)
        crowd.step(
            dt,
            world,
            rng,
            robot.xy,
            cfg.robot.radius,
            robot_heading=float(robot.pose[2]),
            robot_speed=robot.v,
        )


def _ranges(
    cfg: ScenarioConfig,
    info: SensorInfo,
    world: World,
    crowd: Crowd,
    laser: NDArray[Any],
    beam_angles: NDArray[Any],
    streams: list[np.random.Generator],
) -> NDArray[np.float32]:
    """One measured scan from the laser pose: the world and the people, materials, noise."""
    circ, csegs = crowd.shapes()
    true_r = cast_rays(
        laser[:2],
        beam_angles + laser[2],
        np.concatenate([world.segments, csegs]) if len(csegs) else world.segments,
        np.concatenate([world.segment_material, np.zeros(len(csegs), np.int8)]),
        np.concatenate([world.circles, circ]),
        np.concatenate([world.circle_material, np.zeros(len(circ), np.int8)]),
        cfg.materials,
        streams[_MATERIAL],
        max_range=info.range_max * 1.5,
    )
    return measure(true_r, cfg.sensor, info, streams[_SENSOR])


class _Recorder:
    """What a run records: every scan's robot pose and people, and the kept scans."""

    def __init__(
        self, sink: ScanSink | None, keep_scans: bool, middle: int, n_scans: int, n_people: int
    ) -> None:
        self.sink, self.keep_scans, self.middle = sink, keep_scans, middle
        self.scans: list[LaserScan] = []
        self.truth: list[FloatArray] = []
        self.odom: list[FloatArray] = []
        self.n_kept, self.n_inf = 0, 0
        self.middle_scan: LaserScan | None = None
        self.path = np.zeros((n_scans, 3))
        self.tracks = np.zeros((n_scans, n_people, 2))
        self.paused = np.zeros((n_scans, n_people), dtype=bool)

    def state(self, i: int, pose: FloatArray, crowd: Crowd) -> None:
        """Record the robot pose and the people at scan ``i``."""
        self.path[i] = pose
        self.tracks[i] = crowd.pos
        self.paused[i] = crowd.paused

    def result(
        self, seq: ScanSequence, world: World, cfg: ScenarioConfig, crowd: Crowd, n_beams: int
    ) -> SimulationResult:
        """The run's result around its sequence."""
        return SimulationResult(
            sequence=seq,
            world=world,
            config=cfg,
            robot_path=self.path,
            people_tracks=self.tracks,
            people_kinds=crowd.kind.copy(),
            people_paused=self.paused,
            people_followers=crowd.follow.copy(),
            n_kept=self.n_kept,
            inf_fraction=self.n_inf / max(self.n_kept * n_beams, 1),
            middle_scan=self.middle_scan,
        )

    def poses(self) -> tuple[FloatArray | None, FloatArray | None]:
        """The odometry and true poses of the kept scans (None where scans are not kept)."""
        if not self.keep_scans:
            return None, None
        return np.array(self.odom), np.array(self.truth)

    def keep(self, scan: LaserScan, robot: Robot, odo: FloatArray) -> None:
        """Keep a scan with its true and odometry poses (to the sink, and in memory)."""
        pose = robot.pose.copy()
        odo_pose = np.asarray(odo, dtype=np.float64).copy()
        if self.sink is not None:
            self.sink.add(scan, pose, odo_pose)
        if self.keep_scans:
            self.scans.append(scan)
            self.truth.append(pose)
            self.odom.append(odo_pose)
        if self.n_kept == self.middle:
            self.middle_scan = scan
        self.n_kept += 1
        self.n_inf += int(np.count_nonzero(np.isinf(scan.ranges)))


def simulate(
    scenario: str | ScenarioConfig,
    *,
    seed: int,
    duration: float | None = None,
    **overrides: Any,
) -> ScanSequence:
    """Simulate a LiDAR recording in a crowded world with exact ground truth.

    Args:
        scenario: Built-in name (see `SCENARIOS`, `GMAPPING_TRAPS`, `CLOSURE_TRAPS`), a YAML
            path, or a `ScenarioConfig`.
        seed: Seed of everything random; the same seed gives the identical sequence.
        duration: Simulated seconds; None = the scenario's default ``duration`` (the
            `GMAPPING_TRAPS` and `CLOSURE_TRAPS` have one; the paper scenarios do not).
        **overrides: Config overrides, e.g. ``stride=2``, ``people__count=10``,
            ``sensor={"noise_std": 0.0}``; ``progress=True`` shows a progress bar.

    Returns:
        A `ScanSequence` with drifting wheel ``odometry`` (starting at the origin), exact
        ``reference`` poses (``reference_kind="ground_truth"``) and ``metadata["scenario"]``,
        ``metadata["seed"]``.
    """
    progress = bool(overrides.pop("progress", False))
    return simulate_run(
        scenario, seed=seed, duration=duration, progress=progress, **overrides
    ).sequence
