"""Scenario configuration: world, materials, people, sensor, robot, odometry (pydantic/YAML)."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from scanguard.config import YamlModel
from scanguard.errors import ConfigError
from scanguard.scan import SensorInfo

MaterialName = Literal["normal", "glass", "mirror"]

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


class WallSpec(YamlModel):
    """A polyline (or closed polygon) of wall segments with one material."""

    points: list[tuple[float, float]] = Field(min_length=2)
    closed: bool = False
    material: MaterialName = "normal"


class CircleSpec(YamlModel):
    """A round pillar or landmark."""

    center: tuple[float, float]
    radius: float = Field(gt=0)
    material: MaterialName = "normal"


class WorldConfig(YamlModel):
    """Geometry: a built-in random layout generator and/or explicit walls and circles.

    ``params`` values are either a number or a ``[low, high]`` range sampled uniformly per
    variant (so each seed gives another floor plan).
    """

    generator: (
        Literal[
            "lobby", "corridor", "glass", "hall", "office", "atrium", "long_corridor", "building"
        ]
        | None
    ) = None
    params: dict[str, float | tuple[float, float]] = Field(default_factory=dict)
    walls: list[WallSpec] = Field(default_factory=list)
    circles: list[CircleSpec] = Field(default_factory=list)
    #: Robot start (x, y, theta); None = a random free spot (generators suggest one).
    start: tuple[float, float, float] | None = None
    grid_resolution: float = Field(default=0.1, gt=0.01, le=0.5)

    @model_validator(mode="after")
    def _not_empty(self) -> WorldConfig:
        if self.generator is None and not self.walls and not self.circles:
            raise ValueError("a world needs a generator or explicit walls/circles")
        return self


class GlassConfig(YamlModel):
    """Glass panes: per beam, a pane echo, a dropout, or (the rest) pass-through."""

    reflect_prob: float = Field(default=0.12, ge=0, le=1)
    dropout_prob: float = Field(default=0.15, ge=0, le=1)


class MirrorConfig(YamlModel):
    """Mirrors: per beam, a specular bounce (phantom point), a dropout, or a diffuse echo."""

    specular_prob: float = Field(default=0.85, ge=0, le=1)
    dropout_prob: float = Field(default=0.05, ge=0, le=1)


class MaterialsConfig(YamlModel):
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


class PeopleConfig(YamlModel):
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
    leg_radius: float = Field(default=0.06, gt=0)
    carts: int = Field(default=0, ge=0, le=50)
    # social-force parameters (Helbing & Molnar 1995 style)
    relaxation_time: float = Field(default=0.5, gt=0)
    person_strength: float = Field(default=2.0, ge=0)
    person_range: float = Field(default=0.3, gt=0)
    wall_strength: float = Field(default=5.0, ge=0)
    wall_range: float = Field(default=0.2, gt=0)
    robot_strength: float = Field(default=6.0, ge=0)
    robot_range: float = Field(default=0.5, gt=0)
    # --- optional behaviours (all off by default: the built-in paper scenarios do not use them)
    #: Probability that a walker (a group: its leader, for all members) stops for a while when
    #: it reaches its goal (queues, people chatting).
    pause_prob: float = Field(default=0.0, ge=0, le=1)
    #: Rate (1/s) at which a walking walker/group stops on its way.
    pause_rate: float = Field(default=0.0, ge=0)
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
    follow_gain: float = Field(default=1.0, gt=0)
    follow_max_speed: float = Field(default=1.8, gt=0)

    @model_validator(mode="after")
    def _ranges(self) -> PeopleConfig:
        for key in ("pause_duration", "route_offset", "follow_side"):
            lo, hi = getattr(self, key)
            if not 0 <= lo <= hi:
                raise ValueError(f"{key} must be [low, high] with 0 <= low <= high")
        if self.follow_ahead[0] > self.follow_ahead[1]:
            raise ValueError("follow_ahead must be [low, high] with low <= high")
        return self


class SensorConfig(YamlModel):
    """A laser model: a preset plus optional overrides of any of its parameters."""

    model: Literal["rplidar_a3", "sick_lms", "hokuyo_utm30lx", "hokuyo_ust10lx", "pr2_base"] = (
        "rplidar_a3"
    )
    n_beams: int | None = Field(default=None, ge=2)
    fov_deg: float | None = Field(default=None, gt=0, le=360)
    range_min: float | None = Field(default=None, ge=0)
    range_max: float | None = Field(default=None, gt=0)
    rate_hz: float | None = Field(default=None, gt=0)
    #: Range noise std = ``noise_std + noise_rel * range`` (m).
    noise_std: float | None = Field(default=None, ge=0)
    noise_rel: float | None = Field(default=None, ge=0)
    dropout_prob: float = Field(default=0.005, ge=0, le=1)
    #: Probability that a beam on a depth edge returns a mixed pixel (between both surfaces).
    mixed_pixel_prob: float = Field(default=0.0, ge=0, le=1)

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


class RobotConfig(YamlModel):
    """Differential-drive robot (Omorobot R1 defaults) and its motion pattern."""

    radius: float = Field(default=0.3, gt=0)
    max_speed: float = Field(default=1.2, gt=0)
    max_turn_rate: float = Field(default=1.5, gt=0)
    max_accel: float = Field(default=1.0, gt=0)
    max_turn_accel: float = Field(default=3.0, gt=0)
    #: ``patrol``: random straight runs between free points with turns; ``waypoints``: the list;
    #: ``route``: the loop the world generator suggests (``atrium``, ``long_corridor``,
    #: ``building``), at a cruise speed drawn per leg, waiting (never skipping a leg) when
    #: people block the way.
    mode: Literal["patrol", "waypoints", "route"] = "patrol"
    waypoints: list[tuple[float, float]] = Field(default_factory=list)
    loop_waypoints: bool = True
    #: Cruise speed of a straight run is drawn from this range (m/s).
    cruise_speed: tuple[float, float] = (0.8, 1.2)
    min_run: float = Field(default=2.0, ge=0)
    clearance: float = Field(default=0.25, ge=0)
    #: Stop when a person is this close ahead (m) — the robot yields, people avoid it.
    yield_distance: float = Field(default=0.15, ge=0)
    laser_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


class OdometryConfig(YamlModel):
    """Wheel odometry noise per scan interval (odometry motion model, std dev form).

    For a true increment (rot1, trans, rot2): rotations get noise with std
    ``rot_per_rot*|rot| + rot_per_trans*trans``; the translation gets
    ``trans_per_trans*trans + trans_per_rot*(|rot1|+|rot2|)``. ``scale_error`` and
    ``turn_error`` are systematic relative biases (wheel radius / track width errors).
    """

    rot_per_rot: float = Field(default=0.05, ge=0)
    rot_per_trans: float = Field(default=0.02, ge=0)
    trans_per_trans: float = Field(default=0.03, ge=0)
    trans_per_rot: float = Field(default=0.005, ge=0)
    scale_error: float = 0.01
    turn_error: float = -0.015


class ScenarioConfig(YamlModel):
    """A complete simulation scenario (one YAML file)."""

    name: str
    description: str = ""
    environment: int | None = Field(default=None, description="paper Environment number (1-5)")
    world: WorldConfig
    materials: MaterialsConfig = Field(default_factory=lambda: MaterialsConfig())
    people: PeopleConfig = Field(default_factory=lambda: PeopleConfig())
    sensor: SensorConfig = Field(default_factory=lambda: SensorConfig())
    robot: RobotConfig = Field(default_factory=lambda: RobotConfig())
    odometry: OdometryConfig = Field(default_factory=lambda: OdometryConfig())
    #: Scan rate (Hz); None = the sensor's rate.
    scan_rate_hz: float | None = Field(default=None, gt=0)
    #: Keep every ``stride``-th scan (larger inter-scan motions for the same physics).
    stride: int = Field(default=1, ge=1)
    #: Default simulated seconds when `simulate` is called without ``duration``.
    duration: float | None = Field(default=None, gt=0)
    #: Physics step upper bound (s); the scan period is split into equal sub-steps.
    physics_dt: float = Field(default=0.05, gt=0, le=0.2)

    def scan_period(self) -> float:
        """Seconds between simulated scans (before ``stride``)."""
        rate = self.scan_rate_hz or self.sensor.info().rate_hz or 10.0
        return 1.0 / float(rate)


def sample_param(value: float | tuple[float, float], rng: np.random.Generator) -> float:
    """A number, or a uniform draw from a ``(low, high)`` range."""
    if isinstance(value, tuple | list):
        lo, hi = float(value[0]), float(value[1])
        return lo if hi <= lo else float(rng.uniform(lo, hi))
    return float(value)
