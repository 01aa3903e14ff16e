"""Differential-drive robot (Omorobot R1-like): patrol/waypoint controller and wheel odometry."""

from __future__ import annotations

import itertools
import logging
import math

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import ConfigError
from scanguard.geometry import wrap_angle
from scanguard.sim.config import OdometryConfig, RobotConfig
from scanguard.sim.world import World

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class Robot:
    """Unicycle kinematics with speed/acceleration limits and a goal-seeking controller.

    In ``patrol`` mode the robot picks a random visible free point at least ``min_run`` away,
    turns towards it on the spot (fast turns), then drives straight at a cruise speed up to the
    R1's 1.2 m/s. It stops for people right in front of it and never leaves free space.
    In ``waypoints`` mode it follows ``config.waypoints``; in ``route`` mode the loop the world
    generator suggests (``world.route``), at a cruise speed drawn per leg, and when people
    block it, it waits for them instead of skipping a leg.
    """

    def __init__(
        self, config: RobotConfig, world: World, rng: np.random.Generator, start: FloatArray
    ) -> None:
        """Create the robot at ``start`` (validated against the world)."""
        self.cfg = config
        self.world = world
        self.rng = rng
        self.pose = np.asarray(start, dtype=np.float64).copy()
        self.v = 0.0
        self.w = 0.0
        self.cruise = config.max_speed
        self.waiting = 0.0
        #: Route mode: seconds left of squeezing past people beside the lane (after a deadlock).
        self.squeeze = 0.0
        self._wp = 0
        self.target: FloatArray | None = None
        self.margin = config.radius + config.clearance
        #: Waypoints of the ``waypoints``/``route`` modes ``(K, 2)`` (empty in patrol mode).
        self.waypoints = np.zeros((0, 2))
        if not world.is_free(self.pose[None, :2], config.radius)[0]:
            raise ConfigError(f"world {world.name!r}: robot start {self.pose.tolist()} is blocked")
        if config.mode == "waypoints":
            if not config.waypoints:
                raise ConfigError("robot.mode is 'waypoints' but robot.waypoints is empty")
            self.waypoints = np.asarray(config.waypoints, dtype=np.float64).reshape(-1, 2)
        elif config.mode == "route":
            if len(world.route) == 0:
                raise ConfigError(
                    f"robot.mode is 'route' but world {world.name!r} has no route (use the "
                    "atrium, long_corridor, building, twin_rooms or twin_corridors generator, "
                    "or robot.mode: waypoints)"
                )
            self.waypoints = np.asarray(world.route, dtype=np.float64).reshape(-1, 2)
        if len(self.waypoints):
            pts = [self.pose[:2], *self.waypoints]
            for a, b in itertools.pairwise(pts):
                if not world.line_free(a, b, config.radius):
                    raise ConfigError(
                        f"robot.{config.mode}: the straight path {a.tolist()} -> {b.tolist()} "
                        f"hits a wall in world {world.name!r}"
                    )
        #: The driven polyline (start, then the waypoints) ``(K + 1, 2)``; None in patrol mode.
        self.route: FloatArray | None = (
            np.vstack([self.pose[None, :2], self.waypoints]) if len(self.waypoints) else None
        )
        self._next_target()

    @property
    def xy(self) -> FloatArray:
        """Position ``(2,)``."""
        return self.pose[:2]

    def _next_target(self, advance: bool = True) -> None:
        c = self.cfg
        if c.mode == "route":
            # blocked by people or a wall: keep the current leg, never skip one
            if not advance and self.target is not None:
                return
            if self._wp >= len(self.waypoints):
                if not c.loop_waypoints:
                    self.target = None
                    return
                self._wp = 0
            self.target = self.waypoints[self._wp].copy()
            self._wp += 1
            self.cruise = float(self.rng.uniform(*c.cruise_speed))
            return
        if c.mode == "waypoints":
            if self._wp >= len(c.waypoints):
                if not c.loop_waypoints:
                    self.target = None
                    return
                self._wp = 0
            self.target = np.asarray(c.waypoints[self._wp], dtype=np.float64)
            self._wp += 1
            self.cruise = c.max_speed
            return
        best: FloatArray | None = None
        best_len = -1.0
        cands = self.world.sample_free(self.rng, 40, self.margin)
        for cand in cands:
            d = float(np.hypot(*(cand - self.xy)))
            if d < c.min_run or d <= best_len:
                continue
            if self.world.line_free(self.xy, cand, self.margin):
                best, best_len = cand, d
                # prefer long straight runs, but not always the longest possible one
                if self.rng.random() < 0.35:
                    break
        if best is None:
            for cand in cands:
                if self.world.line_free(self.xy, cand, c.radius):
                    best = cand
                    break
        self.target = best
        self.cruise = float(self.rng.uniform(*c.cruise_speed))

    def step(self, dt: float, people_xy: FloatArray, people_r: FloatArray) -> None:
        """Advance by ``dt`` seconds."""
        c = self.cfg
        v_cmd, w_cmd = 0.0, 0.0
        if self.target is None and c.mode == "patrol":
            self._next_target()
        if self.target is not None:
            to = self.target - self.xy
            dist = float(np.hypot(*to))
            err = float(wrap_angle(math.atan2(to[1], to[0]) - self.pose[2]))
            if dist < 0.3:
                self._next_target()
            elif abs(err) > 0.15:
                w_cmd = float(np.clip(3.0 * err, -c.max_turn_rate, c.max_turn_rate))
                v_cmd = 0.0 if abs(err) > 0.5 else 0.3 * self.cruise
            else:
                w_cmd = float(np.clip(2.0 * err, -c.max_turn_rate, c.max_turn_rate))
                # brake in time to stop at the target
                v_cmd = min(self.cruise, math.sqrt(2.0 * c.max_accel * max(dist - 0.2, 0.0)))
        if v_cmd > 0 and people_xy.size:
            rel = people_xy - self.xy
            ch, sh = math.cos(self.pose[2]), math.sin(self.pose[2])
            fwd = rel[:, 0] * ch + rel[:, 1] * sh
            lat = -rel[:, 0] * sh + rel[:, 1] * ch
            # only people in the swept lane ahead block the robot; others can be passed
            margin = 0.0 if self.squeeze > 0.0 else 0.1
            in_lane = (fwd > 0) & (np.abs(lat) < c.radius + people_r + margin)
            gap = float(np.min(np.where(in_lane, fwd - people_r - c.radius, np.inf)))
            # slow down for people ahead and stop when they are within the yield distance
            v_cmd = min(v_cmd, max(0.0, 1.5 * (gap - c.yield_distance)))
            if v_cmd == 0.0:
                self.waiting += dt
                if c.mode == "route" and self.waiting > 8.0:
                    # a route is never skipped: after 8 s, squeeze past people who stand
                    # beside the lane (not on a collision course) for 3 s
                    self.waiting = 0.0
                    self.squeeze = 3.0
                elif c.mode != "route" and self.waiting > 4.0:
                    self.waiting = 0.0
                    self._next_target(advance=False)
            else:
                self.waiting = 0.0
        self.squeeze = max(self.squeeze - dt, 0.0)
        dv = float(np.clip(v_cmd - self.v, -c.max_accel * dt, c.max_accel * dt))
        dw = float(np.clip(w_cmd - self.w, -c.max_turn_accel * dt, c.max_turn_accel * dt))
        v, w = self.v + dv, self.w + dw
        new = self._integrate(self.pose, v, w, dt)
        if self.world.grid().clearance_xy(new[0], new[1]) < c.radius:
            # never into a wall: stop translating and look for another run
            v = 0.0
            new = self._integrate(self.pose, 0.0, w, dt)
            self._next_target(advance=False)
        self.pose, self.v, self.w = new, v, w

    @staticmethod
    def _integrate(pose: FloatArray, v: float, w: float, dt: float) -> FloatArray:
        """Exact unicycle motion over ``dt`` with constant ``v`` and ``w``."""
        if abs(w) < 1e-9:
            sx, sy, a = v * dt, 0.0, 0.0
        else:
            a = w * dt
            sx, sy = v / w * math.sin(a), v / w * (1.0 - math.cos(a))
        c, s = math.cos(pose[2]), math.sin(pose[2])
        th = (pose[2] + a + math.pi) % (2.0 * math.pi) - math.pi
        return np.array([pose[0] + c * sx - s * sy, pose[1] + s * sx + c * sy, th])


def odometry_increment(
    delta: FloatArray, config: OdometryConfig, rng: np.random.Generator
) -> FloatArray:
    """A noisy odometry increment for the true relative motion ``delta`` (robot frame).

    Uses the odometry motion model: ``delta`` is split into rotate-translate-rotate
    (rot1, trans, rot2); each part gets zero-mean Gaussian noise with a standard deviation
    proportional to the motion (see `OdometryConfig`), plus systematic scale/turn errors.

    Args:
        delta: True relative pose ``(dx, dy, dtheta)``.
        config: Noise parameters.
        rng: Noise source (three normal draws per call, always).

    Returns:
        The measured relative pose ``(3,)``.
    """
    dx, dy, dth = (float(v) for v in delta)
    trans = math.hypot(dx, dy)
    rot1 = math.atan2(dy, dx) if trans > 1e-6 else 0.0
    # driving backwards is a negative translation, not a half turn
    if abs(rot1) > math.pi / 2:
        rot1 = float(wrap_angle(rot1 - math.pi))
        trans = -trans
    rot2 = float(wrap_angle(dth - rot1))
    z = rng.standard_normal(3)
    s_r1 = config.rot_per_rot * abs(rot1) + config.rot_per_trans * abs(trans)
    s_t = config.trans_per_trans * abs(trans) + config.trans_per_rot * (abs(rot1) + abs(rot2))
    s_r2 = config.rot_per_rot * abs(rot2) + config.rot_per_trans * abs(trans)
    r1 = rot1 * (1.0 + config.turn_error) + s_r1 * z[0]
    t = trans * (1.0 + config.scale_error) + s_t * z[1]
    r2 = rot2 * (1.0 + config.turn_error) + s_r2 * z[2]
    return np.array([t * math.cos(r1), t * math.sin(r1), float(wrap_angle(r1 + r2))])


def slip_windows(
    config: OdometryConfig, duration: float, rng: np.random.Generator
) -> list[tuple[float, float]]:
    """Start and end (seconds into the run) of the wheel-slip events (see `OdometryConfig`).

    Gaps between events are uniform in ``[0.5, 1.5] * slip_every``, so a run of a few minutes
    sees events at irregular times without long quiet stretches.

    Args:
        config: Odometry settings (``slip_every`` None: no event).
        duration: Simulated seconds.
        rng: The slip stream (drawn from only when the wheels slip).

    Returns:
        The events, in time order.
    """
    if config.slip_every is None:
        return []
    windows: list[tuple[float, float]] = []
    t = config.slip_every * float(rng.uniform(0.5, 1.5))
    while t < duration:
        windows.append((t, min(t + config.slip_duration, duration)))
        t += config.slip_duration + config.slip_every * float(rng.uniform(0.5, 1.5))
    return windows


def slipping(
    t: NDArray[np.float64] | float, windows: list[tuple[float, float]] | list[list[float]]
) -> NDArray[np.bool_]:
    """Whether the step ending at ``t`` lies in a slip window (``start < t <= end``).

    The one test for both the simulator (seconds into the run) and readers of a sequence's
    ``metadata["wheel_slip"]`` (stamps).
    """
    tt = np.asarray(t, dtype=np.float64)
    inside = np.zeros(tt.shape, dtype=bool)
    for a, b in windows:
        inside |= (tt > a) & (tt <= b)
    return inside


def slip_increment(
    t: float, windows: list[tuple[float, float]], speed: float, period: float
) -> FloatArray:
    """The spurious forward motion the wheels add over the step ending at ``t``."""
    return np.array([speed * period if slipping(t, windows) else 0.0, 0.0, 0.0])
