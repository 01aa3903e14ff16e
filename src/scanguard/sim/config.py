"""Scenario configuration: world, materials, people, sensor, robot, odometry (pydantic/YAML)."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator

from scanguard.config import YamlModel
from scanguard.errors import ConfigError
from scanguard.scan import SensorInfo

MaterialName = Literal["normal", "glass", "mirror"]

#: Largest world coordinate (m) of explicit geometry, start and waypoints: worlds span at most
#: 2 km in each direction.
MAX_COORD = 1000.0
#: Largest extent (m) a generator parameter may ask for.
MAX_EXTENT = 2 * MAX_COORD

#: A world coordinate (m): finite and within +-`MAX_COORD`.
Coord = Annotated[float, Field(ge=-MAX_COORD, le=MAX_COORD)]

#: Parameters of each layout generator and their bounds ``(low, high)``: lengths in metres,
#: counts, probabilities. A parameter is a number or a ``[low, high]`` range drawn per seed.
_LENGTH = (0.1, MAX_EXTENT)
_COUNT = (0.0, 100.0)
_PROB = (0.0, 1.0)
_COMMON = {"width": (1.0, MAX_EXTENT), "depth": (1.0, MAX_EXTENT)}
GENERATOR_PARAMS: dict[str, dict[str, tuple[float, float]]] = {
    "lobby": {**_COMMON, "fins": _COUNT, "pillars": _COUNT, "benches": _COUNT},
    "corridor": {"length": (1.0, MAX_EXTENT), "width": (0.5, MAX_EXTENT), "recesses": _COUNT},
    "glass": {
        **_COMMON,
        "outside_depth": _LENGTH,
        "trees": _COUNT,
        "lifts": _COUNT,
        "pillars": _COUNT,
    },
    "hall": {**_COMMON, "pillar_pitch": (2.0, MAX_EXTENT), "pillar_prob": _PROB, "kiosks": _COUNT},
    "office": {**_COMMON, "corridor_width": _LENGTH, "rooms_per_side": (1.0, 100.0)},
    "atrium": {
        **_COMMON,
        "ring": _LENGTH,
        "glass_sides": (0.0, 2.0),
        "outside_depth": _LENGTH,
        "trees": _COUNT,
        "niches": _COUNT,
        "mirrors": _COUNT,
        "block_glass": _PROB,
        "mirror_pillars": _PROB,
        "pillars": _COUNT,
        "benches": _COUNT,
    },
    "long_corridor": {
        "length": (1.0, MAX_EXTENT),
        "width": (0.5, MAX_EXTENT),
        "end_length": _LENGTH,
        "end_width": _LENGTH,
        "doors": _COUNT,
    },
    "building": {
        **_COMMON,
        "room_depth": _LENGTH,
        "corridor_width": _LENGTH,
        "room_width": (0.5, MAX_EXTENT),
        "door": _LENGTH,
        "open_prob": _PROB,
    },
    "twin_rooms": {
        "rooms": (2.0, 20.0),
        "room_width": (3.2, MAX_EXTENT),
        "room_depth": (4.2, MAX_EXTENT),
        "corridor_width": (1.6, MAX_EXTENT),
        "door": (0.9, MAX_EXTENT),
    },
    "twin_corridors": {
        "period": (1.5, MAX_EXTENT),
        "periods": (2.0, 100.0),
        "corridor_width": (1.6, MAX_EXTENT),
        "separation": (3.0, MAX_EXTENT),
    },
}


class _SimModel(YamlModel):
    """Scenario models: strict like every config, and every number must be finite."""

    model_config = ConfigDict(allow_inf_nan=False)


def _check_range(name: str, value: tuple[float, float], low: float, high: float) -> None:
    """Raise ValueError unless ``low <= value[0] <= value[1] <= high``."""
    lo, hi = value
    if lo > hi:
        raise ValueError(f"{name} [{lo}, {hi}] is reversed: give [low, high] with low <= high")
    if lo < low or hi > high:
        raise ValueError(f"{name} [{lo}, {hi}] must lie within [{low}, {high}]")


#: Built-in sensor presets: ``(n_beams, fov_deg, range_min, range_max, rate_hz, noise_std,
#: noise_rel)``. Angles are centred on the sensor x axis.
SENSOR_PRESETS: dict[str, dict[str, float | int | str]] = {
    "rplidar_a3": {
        "name": "RPLidar A3",
        "n_beams": 1440,
        "fov_deg": 360.0,
        "range_min": 0.15,
        "range_max": 25.0,
        "rate_hz": 10.0,
        "noise_std": 0.01,
        "noise_rel": 0.005,
    },
    "sick_lms": {
        "name": "SICK LMS 200",
        "n_beams": 181,
        "fov_deg": 180.0,
        "range_min": 0.1,
        "range_max": 80.0,
        "rate_hz": 10.0,
        "noise_std": 0.01,
        "noise_rel": 0.0,
    },
    "hokuyo_utm30lx": {
        "name": "Hokuyo UTM-30LX",
        "n_beams": 1081,
        "fov_deg": 270.0,
        "range_min": 0.1,
        "range_max": 30.0,
        "rate_hz": 40.0,
        "noise_std": 0.01,
        "noise_rel": 0.0,
    },
    "hokuyo_ust10lx": {
        "name": "Hokuyo UST-10LX",
        "n_beams": 1081,
        "fov_deg": 270.0,
        "range_min": 0.06,
        "range_max": 10.0,
        "rate_hz": 40.0,
        "noise_std": 0.015,
        "noise_rel": 0.0,
    },
    "pr2_base": {
        "name": "PR2 base laser (Hokuyo UTM-30LX, 1040 beams)",
        "n_beams": 1040,
        "fov_deg": 270.0,
        "range_min": 0.023,
        "range_max": 30.0,
        "rate_hz": 20.0,
        "noise_std": 0.01,
        "noise_rel": 0.0,
    },
}


class WallSpec(_SimModel):
    """A polyline (or closed polygon) of wall segments with one material."""

    points: list[tuple[Coord, Coord]] = Field(min_length=2, max_length=100_000)
    closed: bool = False
    material: MaterialName = "normal"


class CircleSpec(_SimModel):
    """A round pillar or landmark."""

    center: tuple[Coord, Coord]
    radius: float = Field(gt=0, le=MAX_COORD)
    material: MaterialName = "normal"


class WorldConfig(_SimModel):
    """Geometry: a built-in random layout generator and/or explicit walls and circles.

    ``params`` values are either a number or a ``[low, high]`` range sampled uniformly per
    variant (so each seed gives another floor plan); each generator accepts the parameters
    listed in `GENERATOR_PARAMS`, within their bounds.
    """

    generator: (
        Literal[
            "lobby",
            "corridor",
            "glass",
            "hall",
            "office",
            "atrium",
            "long_corridor",
            "building",
            "twin_rooms",
            "twin_corridors",
        ]
        | None
    ) = None
    params: dict[str, float | tuple[float, float]] = Field(default_factory=dict)
    walls: list[WallSpec] = Field(default_factory=list, max_length=100_000)
    circles: list[CircleSpec] = Field(default_factory=list, max_length=100_000)
    #: Robot start (x, y, theta); None = a random free spot (generators suggest one).
    start: tuple[Coord, Coord, Annotated[float, Field(ge=-10.0, le=10.0)]] | None = None
    grid_resolution: float = Field(default=0.1, gt=0.01, le=0.5)

    @field_validator("params", mode="before")
    @classmethod
    def _params_shape(cls, value: Any) -> Any:
        # a clear message for a bad value instead of pydantic's union errors
        if not isinstance(value, dict):
            return value
        out: dict[Any, Any] = {}
        for key, val in value.items():
            if isinstance(val, list | tuple):
                if len(val) != 2 or not all(_is_number(v) for v in val):
                    raise ValueError(f"{key}: expected a number or [low, high], got {val!r}")
                pair = (float(val[0]), float(val[1]))
                if not all(math.isfinite(v) for v in pair):
                    raise ValueError(f"{key}: {list(pair)} is not finite")
                out[key] = pair
            elif _is_number(val):
                if not math.isfinite(float(val)):
                    raise ValueError(f"{key}: {val} is not finite")
                out[key] = float(val)
            else:
                raise ValueError(f"{key}: expected a number or [low, high], got {val!r}")
        return out

    @model_validator(mode="after")
    def _not_empty(self) -> WorldConfig:
        if self.generator is None and not self.walls and not self.circles:
            raise ValueError("a world needs a generator or explicit walls/circles")
        if self.params and self.generator is None:
            raise ValueError("params need a generator")
        if self.generator is not None:
            known = GENERATOR_PARAMS[self.generator]
            for key, val in self.params.items():
                if key not in known:
                    raise ValueError(
                        f"params.{key}: unknown parameter of generator {self.generator!r} "
                        f"(known: {', '.join(sorted(known))})"
                    )
                pair = val if isinstance(val, tuple) else (val, val)
                _check_range(f"params.{key}", pair, *known[key])
        return self


class GlassConfig(_SimModel):
    """Glass panes: per beam, a pane echo, a dropout, or (the rest) pass-through."""

    reflect_prob: float = Field(default=0.12, ge=0, le=1)
    dropout_prob: float = Field(default=0.15, ge=0, le=1)


class MirrorConfig(_SimModel):
    """Mirrors: per beam, a specular bounce (phantom point), a dropout, or a diffuse echo."""

    specular_prob: float = Field(default=0.85, ge=0, le=1)
    dropout_prob: float = Field(default=0.05, ge=0, le=1)


class MaterialsConfig(_SimModel):
    """Optical behaviour of the non-normal materials."""

    glass: GlassConfig = Field(default_factory=lambda: GlassConfig())
    mirror: MirrorConfig = Field(default_factory=lambda: MirrorConfig())
    max_bounces: int = Field(default=4, ge=1, le=16)

    @model_validator(mode="after")
    def _probabilities(self) -> MaterialsConfig:
        if self.glass.reflect_prob + self.glass.dropout_prob > 1.0:
            raise ValueError("glass reflect_prob + dropout_prob must be <= 1")
        if self.mirror.specular_prob + self.mirror.dropout_prob > 1.0:
            raise ValueError("mirror specular_prob + dropout_prob must be <= 1")
        return self


class PeopleConfig(_SimModel):
    """Pedestrians (social-force model) and optional carts."""

    count: int = Field(default=30, ge=0, le=500)
    speed: tuple[float, float] = (0.5, 1.5)
    standing_fraction: float = Field(default=0.15, ge=0, le=1)
    group_fraction: float = Field(default=0.3, ge=0, le=1)
    group_size: tuple[int, int] = (2, 4)
    #: Fraction of walkers that pick goals near the robot (close passes, big occlusions).
    approach_fraction: float = Field(default=0.3, ge=0, le=1)
    #: Fraction of people seen as two swinging legs (the rest as a body circle).
    legs_fraction: float = Field(default=0.5, ge=0, le=1)
    body_radius: tuple[float, float] = (0.18, 0.28)
    leg_radius: float = Field(default=0.06, gt=0, le=0.5)
    carts: int = Field(default=0, ge=0, le=50)
    # social-force parameters (Helbing & Molnar 1995 style)
    relaxation_time: float = Field(default=0.5, gt=0, le=100)
    person_strength: float = Field(default=2.0, ge=0, le=1000)
    person_range: float = Field(default=0.3, gt=0, le=100)
    wall_strength: float = Field(default=5.0, ge=0, le=1000)
    wall_range: float = Field(default=0.2, gt=0, le=100)
    robot_strength: float = Field(default=6.0, ge=0, le=1000)
    robot_range: float = Field(default=0.5, gt=0, le=100)
    # --- optional behaviours (all off by default: the built-in paper scenarios do not use them)
    #: Probability that a walker (a group: its leader, for all members) stops for a while when
    #: it reaches its goal (queues, people chatting).
    pause_prob: float = Field(default=0.0, ge=0, le=1)
    #: Rate (1/s) at which a walking walker/group stops on its way.
    pause_rate: float = Field(default=0.0, ge=0, le=1000)
    #: Length of a stop (s), drawn uniformly per stop.
    pause_duration: tuple[float, float] = (4.0, 15.0)
    #: Fraction of walkers whose goals are beside the robot's route (``robot.mode: route``), so
    #: that, when they stop there, they occlude the walls along it for long periods.
    route_fraction: float = Field(default=0.0, ge=0, le=1)
    #: Lateral distance (m) of those goals from the route.
    route_offset: tuple[float, float] = (0.9, 2.0)
    #: Number of walkers that walk alongside the robot: each keeps a fixed place in the robot
    #: frame (``follow_ahead`` metres ahead, ``follow_side`` metres to the left or right,
    #: alternating), moving with the robot's velocity. Structure that moves with the sensor.
    follow_count: int = Field(default=0, ge=0, le=100)
    follow_ahead: tuple[float, float] = (-0.5, 3.0)
    follow_side: tuple[float, float] = (1.0, 2.2)
    #: Gain (1/s) pulling a follower back to its place; the speed is capped at
    #: ``follow_max_speed`` (m/s).
    follow_gain: float = Field(default=1.0, gt=0, le=100)
    follow_max_speed: float = Field(default=1.8, gt=0, le=10)
    #: Number of people (the last ``gather_count`` of ``count``) that gather at
    #: ``gather_point`` and stand there: until their ``gather_time`` (s, drawn per person) they
    #: walk among points at least ``gather_spawn_distance`` m from it that have a clear view of
    #: it, then walk to a spot within ``gather_radius`` m of the point and at least
    #: ``gather_lane`` m beside the robot's route, and stay there to the end of the run (a crowd
    #: that fills a place after the robot has passed it).
    gather_count: int = Field(default=0, ge=0, le=500)
    #: Where they gather; None = the robot's start (a loop's closing point).
    gather_point: tuple[Coord, Coord] | None = None
    gather_time: tuple[float, float] = (20.0, 40.0)
    gather_radius: float = Field(default=3.0, gt=0, le=100)
    gather_lane: float = Field(default=0.9, ge=0, le=100)
    gather_spawn_distance: float = Field(default=8.0, ge=0, le=MAX_EXTENT)

    @model_validator(mode="after")
    def _ranges(self) -> PeopleConfig:
        for key, low, high in (
            ("speed", 0.0, 5.0),
            ("body_radius", 0.01, 2.0),
            ("pause_duration", 0.0, 3600.0),
            ("route_offset", 0.0, 100.0),
            ("follow_side", 0.0, 100.0),
            ("follow_ahead", -100.0, 100.0),
            ("gather_time", 0.0, 1e6),
        ):
            _check_range(key, getattr(self, key), low, high)
        lo, hi = self.group_size
        _check_range("group_size", (float(lo), float(hi)), 1.0, 50.0)
        if self.gather_count > self.count:
            raise ValueError(f"gather_count {self.gather_count} exceeds count {self.count}")
        return self


class SensorConfig(_SimModel):
    """A laser model: a preset plus optional overrides of any of its parameters."""

    model: Literal["rplidar_a3", "sick_lms", "hokuyo_utm30lx", "hokuyo_ust10lx", "pr2_base"] = (
        "rplidar_a3"
    )
    n_beams: int | None = Field(default=None, ge=2, le=10_000)
    fov_deg: float | None = Field(default=None, gt=0, le=360)
    range_min: float | None = Field(default=None, ge=0, le=1000)
    range_max: float | None = Field(default=None, gt=0, le=1000)
    rate_hz: float | None = Field(default=None, ge=0.1, le=100)
    #: Range noise std = ``noise_std + noise_rel * range`` (m).
    noise_std: float | None = Field(default=None, ge=0, le=10)
    noise_rel: float | None = Field(default=None, ge=0, le=1)
    dropout_prob: float = Field(default=0.005, ge=0, le=1)
    #: Probability that a beam on a depth edge returns a mixed pixel (between both surfaces).
    mixed_pixel_prob: float = Field(default=0.0, ge=0, le=1)

    @model_validator(mode="after")
    def _limits(self) -> SensorConfig:
        rmin, rmax = self._value("range_min"), self._value("range_max")
        if rmin >= rmax:
            raise ValueError(f"range_min {rmin} must be < range_max {rmax}")
        return self

    def _value(self, key: str) -> float:
        own = getattr(self, key)
        return float(SENSOR_PRESETS[self.model][key] if own is None else own)

    @property
    def sigma(self) -> tuple[float, float]:
        """Resolved ``(noise_std, noise_rel)``."""
        return self._value("noise_std"), self._value("noise_rel")

    def info(self) -> SensorInfo:
        """The resolved `SensorInfo` (beams evenly spaced, centred on the x axis)."""
        n = int(self._value("n_beams"))
        fov = math.radians(self._value("fov_deg"))
        rmin, rmax = self._value("range_min"), self._value("range_max")
        if rmin >= rmax:
            raise ConfigError(f"sensor {self.model}: range_min {rmin} >= range_max {rmax}")
        # a full circle must not repeat the first beam at +pi
        inc = fov / n if fov >= 2 * math.pi - 1e-9 else fov / (n - 1)
        amin = -math.pi if fov >= 2 * math.pi - 1e-9 else -fov / 2
        return SensorInfo(
            name=str(SENSOR_PRESETS[self.model]["name"]),
            n_beams=n,
            angle_min=amin,
            angle_increment=inc,
            range_min=rmin,
            range_max=rmax,
            rate_hz=self._value("rate_hz"),
        )


class RobotConfig(_SimModel):
    """Differential-drive robot (Omorobot R1 defaults) and its motion pattern."""

    radius: float = Field(default=0.3, gt=0, le=5)
    max_speed: float = Field(default=1.2, gt=0, le=10)
    max_turn_rate: float = Field(default=1.5, gt=0, le=20)
    max_accel: float = Field(default=1.0, gt=0, le=100)
    max_turn_accel: float = Field(default=3.0, gt=0, le=100)
    #: ``patrol``: random straight runs between free points with turns; ``waypoints``: the list;
    #: ``route``: the loop the world generator suggests (``atrium``, ``long_corridor``,
    #: ``building``, ``twin_rooms``, ``twin_corridors``), at a cruise speed drawn per leg,
    #: waiting (never skipping a leg) when people block the way.
    mode: Literal["patrol", "waypoints", "route"] = "patrol"
    waypoints: list[tuple[Coord, Coord]] = Field(default_factory=list, max_length=100_000)
    loop_waypoints: bool = True
    #: Cruise speed of a straight run is drawn from this range (m/s).
    cruise_speed: tuple[float, float] = (0.8, 1.2)
    min_run: float = Field(default=2.0, ge=0, le=MAX_EXTENT)
    clearance: float = Field(default=0.25, ge=0, le=10)
    #: Stop when a person is this close ahead (m) — the robot yields, people avoid it.
    yield_distance: float = Field(default=0.15, ge=0, le=10)
    laser_offset: tuple[
        Annotated[float, Field(ge=-10, le=10)],
        Annotated[float, Field(ge=-10, le=10)],
        Annotated[float, Field(ge=-10, le=10)],
    ] = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _ranges(self) -> RobotConfig:
        _check_range("cruise_speed", self.cruise_speed, 0.0, 10.0)
        return self


class OdometryConfig(_SimModel):
    """Wheel odometry noise per scan interval (odometry motion model, std dev form).

    For a true increment (rot1, trans, rot2): rotations get noise with std
    ``rot_per_rot*|rot| + rot_per_trans*trans``; the translation gets
    ``trans_per_trans*trans + trans_per_rot*(|rot1|+|rot2|)``. ``scale_error`` and
    ``turn_error`` are systematic relative biases (wheel radius / track width errors).
    With ``slip_every``, the wheels also slip now and then: for ``slip_duration`` seconds they
    report ``slip_speed`` of forward motion the robot did not make.
    """

    rot_per_rot: float = Field(default=0.05, ge=0, le=10)
    rot_per_trans: float = Field(default=0.02, ge=0, le=10)
    trans_per_trans: float = Field(default=0.03, ge=0, le=10)
    trans_per_rot: float = Field(default=0.005, ge=0, le=10)
    scale_error: float = Field(default=0.01, ge=-0.9, le=0.9)
    turn_error: float = Field(default=-0.015, ge=-0.9, le=0.9)
    #: Mean seconds between wheel-slip events (None: the wheels never slip). Event starts are
    #: drawn from their own random stream, so a scenario without slip simulates as before.
    slip_every: float | None = Field(default=None, gt=0, le=1e6)
    #: Seconds one slip event lasts.
    slip_duration: float = Field(default=2.0, gt=0, le=1e6)
    #: Forward speed (m/s) the wheels report on top of the true motion while they slip
    #: (wheels spinning on a wet or dusty floor, or turning while people hold the robot).
    slip_speed: float = Field(default=0.5, ge=0, le=100)


class ScenarioConfig(_SimModel):
    """A complete simulation scenario (one YAML file)."""

    name: str = Field(min_length=1, max_length=200)
    description: str = Field(default="", max_length=10_000)
    environment: int | None = Field(
        default=None, ge=0, le=1000, description="paper Environment number (1-5)"
    )
    world: WorldConfig
    materials: MaterialsConfig = Field(default_factory=lambda: MaterialsConfig())
    people: PeopleConfig = Field(default_factory=lambda: PeopleConfig())
    sensor: SensorConfig = Field(default_factory=lambda: SensorConfig())
    robot: RobotConfig = Field(default_factory=lambda: RobotConfig())
    odometry: OdometryConfig = Field(default_factory=lambda: OdometryConfig())
    #: Scan rate (Hz); None = the sensor's rate.
    scan_rate_hz: float | None = Field(default=None, ge=0.1, le=100)
    #: Keep every ``stride``-th scan (larger inter-scan motions for the same physics).
    stride: int = Field(default=1, ge=1, le=1000)
    #: Default simulated seconds when `simulate` is called without ``duration`` (bounded by
    #: the run budget, see `scanguard.sim.limits`).
    duration: float | None = Field(default=None, gt=0)
    #: Physics step upper bound (s); the scan period is split into equal sub-steps.
    physics_dt: float = Field(default=0.05, ge=0.001, le=0.2)

    def scan_period(self) -> float:
        """Seconds between simulated scans (before ``stride``)."""
        rate = self.scan_rate_hz or self.sensor.info().rate_hz or 10.0
        return 1.0 / float(rate)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def sample_param(value: float | tuple[float, float], rng: np.random.Generator) -> float:
    """A number, or a uniform draw from a ``(low, high)`` range."""
    if isinstance(value, tuple | list):
        lo, hi = float(value[0]), float(value[1])
        return lo if hi <= lo else float(rng.uniform(lo, hi))
    return float(value)
