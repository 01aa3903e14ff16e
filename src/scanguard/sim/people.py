"""Pedestrians (and carts) driven by a small vectorised social-force model.

Every agent walks towards a goal it can see, is pushed away from other agents, walls and the
robot, and keeps near its group. The laser sees walkers either as two swinging legs or as one
body circle; carts are boxes.

Optional behaviours (off by default, see `PeopleConfig`): walkers that stop for a while (on
arrival or on the way; a group stops together), walkers whose goals lie beside the robot's route,
followers that walk alongside the robot at a fixed place in its frame, and a crowd that gathers
at one place (e.g. a loop's closing point) at a given time and stands there.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanguard.sim.config import PeopleConfig
from scanguard.sim.placement import gather_spots, place_agents, place_followers
from scanguard.sim.social_force import social_forces
from scanguard.sim.world import World

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

LEGS, BODY, CART = 0, 1, 2
_CART_SIZE = (1.0, 0.6)


def _kinds(config: PeopleConfig, rng: np.random.Generator) -> tuple[NDArray[np.int8], FloatArray]:
    """The kind (legs, body or cart) and radius of every agent: people first, then carts."""
    n_people, n_carts = config.count, config.carts
    n = n_people + n_carts
    kind = np.full(n, BODY, dtype=np.int8)
    kind[:n_people][rng.random(n_people) < config.legs_fraction] = LEGS
    kind[n_people:] = CART
    radius = np.where(kind == CART, 0.6, rng.uniform(*config.body_radius, size=n))
    radius = np.where(kind == LEGS, 0.22, radius)
    return kind, radius


def _follow_offsets(config: PeopleConfig, rng: np.random.Generator, k: int) -> FloatArray:
    """The places of ``k`` followers in the robot's frame ``(k, 2)`` (ahead, side)."""
    side = rng.uniform(*config.follow_side, size=k)
    # alternate left/right so that the robot is flanked on both sides
    side *= np.where(np.arange(k) % 2 == 0, 1.0, -1.0)
    return np.column_stack([rng.uniform(*config.follow_ahead, size=k), side])


def _route_goers(
    config: PeopleConfig,
    rng: np.random.Generator,
    route: FloatArray,
    kind: NDArray[np.int8],
    gather: NDArray[np.bool_],
    busy: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Walkers whose goals lie beside the robot's route (none of the ``busy`` ones)."""
    n = len(kind)
    route_goer = np.zeros(n, dtype=bool)
    if config.route_fraction > 0:
        if len(route) < 2:
            log.warning("people.route_fraction is set but the robot has no route: ignored")
        else:
            route_goer = (rng.random(n) < config.route_fraction) & ~busy
            route_goer &= (kind != CART) & ~gather
    return route_goer


def _gathering(
    config: PeopleConfig,
    world: World,
    rng: np.random.Generator,
    center: FloatArray,
    radius: FloatArray,
    gather: NDArray[np.bool_],
    route: FloatArray,
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """When (s) and where the gatherers gather, and the gatherers that got a spot."""
    n = len(radius)
    gather_at = np.zeros(n)
    gather_spot = np.zeros((n, 2))
    if gather.any():
        gather_at[gather] = rng.uniform(*config.gather_time, size=int(gather.sum()))
        gather_spot, gather = gather_spots(config, world, rng, center, radius, gather, route)
    return gather_at, gather_spot, gather


def _roles(
    config: PeopleConfig,
    rng: np.random.Generator,
    kind: NDArray[np.int8],
    gather: NDArray[np.bool_],
    v0: FloatArray,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.int64], NDArray[np.bool_]]:
    """Followers, standing agents, walking groups and approachers (``v0`` set to match).

    Returns:
        ``(follow, standing, group, approach)``: masks ``(N,)`` and group ids (-1: none).
    """
    n = len(kind)
    # followers are the first people (spawned near the robot); with follow_count 0 the
    # masks below are all False and every draw is the same as without this feature
    follow = np.zeros(n, dtype=bool)
    follow[np.nonzero(kind != CART)[0][: config.follow_count]] = True
    standing = (rng.random(n) < config.standing_fraction) & (kind != CART) & ~follow
    standing &= ~gather
    v0[standing] = 0.0
    group = np.full(n, -1, dtype=np.int64)
    walkers = np.nonzero(~standing & (kind != CART) & ~follow & ~gather)[0]
    rng.shuffle(walkers)
    n_grouped = round(config.group_fraction * walkers.size)
    i, gid = 0, 0
    while i < n_grouped - 1:
        size = int(rng.integers(config.group_size[0], config.group_size[1] + 1))
        members = walkers[i : min(i + size, n_grouped)]
        group[members] = gid
        v0[members] = v0[members[0]]
        gid += 1
        i += size
    approach = (rng.random(n) < config.approach_fraction) & ~standing & ~follow & ~gather
    return follow, standing, group, approach


@dataclass
class Crowd:
    """State of all agents (arrays of length N)."""

    pos: FloatArray
    vel: FloatArray
    goal: FloatArray
    v0: FloatArray
    radius: FloatArray
    kind: NDArray[np.int8]
    group: NDArray[np.int64]
    approach: NDArray[np.bool_]
    heading: FloatArray
    phase: FloatArray
    stuck: FloatArray
    goal_offset: FloatArray
    config: PeopleConfig
    #: Seconds each agent still stands (> 0: stopped; only with pauses enabled).
    pause_left: FloatArray
    #: Followers: walk alongside the robot at ``follow_offset`` (robot frame).
    follow: NDArray[np.bool_]
    follow_offset: FloatArray
    #: Walkers whose goals lie beside ``route``.
    route_goer: NDArray[np.bool_]
    #: The robot's route polyline ``(K, 2)`` (may be empty).
    route: FloatArray
    #: Agents that gather at a place: after ``gather_at`` (s) they walk to ``gather_spot``
    #: and stand there.
    gather: NDArray[np.bool_]
    gather_at: FloatArray
    gather_spot: FloatArray
    #: Where they gather ``(2,)``; before their time they walk among points at least
    #: ``gather_spawn_distance`` m from it that they can see it from.
    gather_center: FloatArray
    #: Simulated seconds since the crowd was spawned.
    time: float = 0.0

    @property
    def n(self) -> int:
        """Number of agents."""
        return int(self.pos.shape[0])

    @property
    def paused(self) -> NDArray[np.bool_]:
        """Agents stopped by a pause right now ``(N,)`` (standing agents are not paused)."""
        return self.pause_left > 0.0

    @classmethod
    def spawn(
        cls,
        config: PeopleConfig,
        world: World,
        rng: np.random.Generator,
        robot_xy: FloatArray,
        robot_radius: float,
        *,
        robot_heading: float = 0.0,
        route: FloatArray | None = None,
    ) -> Crowd:
        """Place ``config.count`` people and ``config.carts`` carts on free, separate spots.

        Args:
            config: People parameters.
            world: The static world.
            rng: The people's random stream.
            robot_xy: Robot position ``(2,)``.
            robot_radius: Robot radius (m).
            robot_heading: Robot heading (rad): followers start at their place beside it.
            route: The robot's route ``(K, 2)`` for ``route_fraction`` walkers (None: none).

        Returns:
            The crowd.
        """
        n_people = config.count
        kind, radius = _kinds(config, rng)
        n = len(kind)
        pos, placed, gather, center = place_agents(
            config, world, rng, robot_xy, robot_radius, radius, n_people
        )
        if len(placed) < n:
            log.warning("only %d of %d agents fit into world %s", len(placed), n, world.name)
            keep = np.array(sorted(placed), dtype=np.intp)
            pos, kind, radius = pos[keep], kind[keep], radius[keep]
            gather = gather[keep]
            n = len(keep)
        v0 = rng.uniform(*config.speed, size=n)
        follow, standing, group, approach = _roles(config, rng, kind, gather, v0)
        route_xy = np.zeros((0, 2)) if route is None else np.asarray(route, dtype=np.float64)
        route_goer = _route_goers(config, rng, route_xy, kind, gather, standing | follow | approach)
        follow_offset = np.zeros((n, 2))
        if follow.any():
            follow_offset[follow] = _follow_offsets(config, rng, int(follow.sum()))
            v0[follow] = config.follow_max_speed
            pos = place_followers(
                pos, radius, follow, follow_offset, world, robot_xy, robot_heading, robot_radius
            )
        gather_at, gather_spot, gather = _gathering(
            config, world, rng, center, radius, gather, route_xy
        )
        crowd = cls(
            pos=pos,
            vel=np.zeros((n, 2)),
            goal=pos.copy(),
            v0=v0,
            radius=radius,
            kind=kind,
            group=group,
            approach=approach,
            heading=rng.uniform(-np.pi, np.pi, size=n),
            phase=rng.uniform(0, 2 * np.pi, size=n),
            stuck=np.zeros(n),
            goal_offset=rng.normal(0.0, 0.5, size=(n, 2)),
            config=config,
            pause_left=np.zeros(n),
            follow=follow,
            follow_offset=follow_offset,
            route_goer=route_goer,
            route=route_xy,
            gather=gather,
            gather_at=gather_at,
            gather_spot=gather_spot,
            gather_center=center,
        )
        crowd._new_goals(np.ones(n, dtype=bool) & ~follow, world, rng, robot_xy)
        if follow.any():
            crowd.goal[follow] = crowd._follow_targets(robot_xy, robot_heading)
        return crowd

    # ------------------------------------------------------------------------------------

    def _new_goals(
        self, need: NDArray[np.bool_], world: World, rng: np.random.Generator, robot_xy: FloatArray
    ) -> None:
        moving = self.v0 > 0
        for i in np.nonzero(need & moving)[0]:
            g = self.group[i]
            if g >= 0:
                leader = int(np.nonzero(self.group == g)[0][0])
                if leader != i:
                    continue
            goal = None
            if self.gather[i]:
                goal = self._gather_wait_goal(int(i), world, rng)
            if goal is None and self.route_goer[i]:
                goal = self._route_goal(int(i), world, rng)
            if goal is None and self.approach[i]:
                # walk past the robot to its far side: close passes that occlude large sectors
                away = robot_xy - self.pos[i]
                away = away / max(float(np.hypot(*away)), 1e-6)
                cand = robot_xy + away * rng.uniform(2.0, 6.0, size=(6, 1))
                cand = cand + rng.normal(0.0, 0.8, size=(6, 2))
                for c in cand:
                    if world.is_free(c[None], 0.5)[0] and world.line_free(self.pos[i], c, 0.3):
                        goal = c
                        break
            if goal is None:
                cand = world.sample_free(rng, 12, 0.5)
                dist = np.hypot(*(cand - self.pos[i]).T)
                for j in np.argsort(-dist):
                    if dist[j] > 2.0 and world.line_free(self.pos[i], cand[j], 0.3):
                        goal = cand[j]
                        break
            if goal is None:
                goal = world.sample_free(rng, 1, 0.5)[0]
            self.goal[i] = goal
            self.stuck[i] = 0.0
            if g >= 0:
                members = np.nonzero(self.group == g)[0]
                self.goal[members] = goal + self.goal_offset[members]
                self.stuck[members] = 0.0

    def _gather_wait_goal(
        self, i: int, world: World, rng: np.random.Generator
    ) -> FloatArray | None:
        """A goal for a gatherer before its time: far from the gathering place, in sight of it.

        Keeps the place empty until the crowd comes and gives every gatherer a straight walk
        to it (None when no such point is found).
        """
        cand = world.sample_free(rng, 30, 0.5)
        far = np.hypot(*(cand - self.gather_center).T) > self.config.gather_spawn_distance
        for c in cand[far]:
            if world.line_free(c, self.gather_center, 0.3) and world.line_free(self.pos[i], c, 0.3):
                return np.asarray(c, dtype=np.float64)
        return None

    def _route_goal(self, i: int, world: World, rng: np.random.Generator) -> FloatArray | None:
        """A visible free point beside the robot's route (None when none is found)."""
        a, b = self.route[:-1], self.route[1:]
        length = np.hypot(*(b - a).T)
        if length.sum() <= 0:
            return None
        seg = rng.choice(len(a), size=6, p=length / length.sum())
        t = rng.uniform(0.0, 1.0, size=6)
        lo, hi = self.config.route_offset
        off = rng.uniform(lo, hi, size=6) * rng.choice(np.array([-1.0, 1.0]), size=6)
        along = (b[seg] - a[seg]) / np.maximum(length[seg], 1e-9)[:, None]
        normal = np.column_stack([-along[:, 1], along[:, 0]])
        cand = a[seg] + t[:, None] * (b[seg] - a[seg]) + off[:, None] * normal
        for c in cand:
            if world.is_free(c[None], 0.5)[0] and world.line_free(self.pos[i], c, 0.3):
                return np.asarray(c, dtype=np.float64)
        return None

    def _follow_targets(self, robot_xy: FloatArray, robot_heading: float) -> FloatArray:
        """World positions of the followers' places beside the robot ``(F, 2)``."""
        ch, sh = math.cos(robot_heading), math.sin(robot_heading)
        off = self.follow_offset[self.follow]
        return np.column_stack(
            [
                robot_xy[0] + ch * off[:, 0] - sh * off[:, 1],
                robot_xy[1] + sh * off[:, 0] + ch * off[:, 1],
            ]
        )

    def _leaders(self) -> NDArray[np.bool_]:
        """Agents that decide for themselves: ungrouped ones and each group's first member."""
        first = np.zeros(self.n, dtype=bool)
        grouped = np.nonzero(self.group >= 0)[0]
        if grouped.size:
            _, idx = np.unique(self.group[grouped], return_index=True)
            first[grouped[idx]] = True
        return (self.group < 0) | first

    def _start_pauses(self, start: NDArray[np.bool_], rng: np.random.Generator) -> None:
        """Stop the agents (leaders: with their whole group) in ``start`` for a random time."""
        idx = np.nonzero(start)[0]
        if idx.size == 0:
            return
        dur = rng.uniform(*self.config.pause_duration, size=idx.size)
        for i, d in zip(idx, dur, strict=True):
            g = self.group[i]
            members = np.nonzero(self.group == g)[0] if g >= 0 else np.array([i])
            self.pause_left[members] = d

    def step(
        self,
        dt: float,
        world: World,
        rng: np.random.Generator,
        robot_xy: FloatArray,
        robot_radius: float,
        *,
        robot_heading: float = 0.0,
        robot_speed: float = 0.0,
    ) -> None:
        """Advance all agents by ``dt`` seconds (social forces, then hard collision checks).

        Args:
            dt: Time step (s).
            world: The static world.
            rng: The people's random stream.
            robot_xy: Robot position ``(2,)``.
            robot_radius: Robot radius (m).
            robot_heading: Robot heading (rad), used by followers only.
            robot_speed: Robot forward speed (m/s), used by followers only.
        """
        if self.n == 0:
            return
        c = self.config
        pausing = c.pause_prob > 0 or c.pause_rate > 0
        followers = bool(self.follow.any())
        if followers:
            self.goal[self.follow] = self._follow_targets(robot_xy, robot_heading)
        self.time += dt
        # gatherers on their way to (or standing at) their spot keep it as their goal
        going = self.gather & (self.time >= self.gather_at)
        if going.any():
            self.goal[going] = self.gather_spot[going]
        to_goal = self.goal - self.pos
        dgoal = np.hypot(to_goal[:, 0], to_goal[:, 1])
        e = to_goal / np.maximum(dgoal, 1e-6)[:, None]
        desired = e * (self.v0 * np.minimum(1.0, dgoal / 0.5))[:, None]
        if followers:
            # keep the place beside the robot: the robot's velocity plus a pull to the place
            vr = robot_speed * np.array([math.cos(robot_heading), math.sin(robot_heading)])
            want = vr + c.follow_gain * to_goal[self.follow]
            sp_w = np.hypot(want[:, 0], want[:, 1])
            want *= np.minimum(1.0, c.follow_max_speed / np.maximum(sp_w, 1e-9))[:, None]
            desired[self.follow] = want
        if pausing:
            desired[self.paused] = 0.0
        self._move(desired, dt, world, robot_xy, robot_radius, pausing)
        reached = dgoal < 0.6
        if not (pausing or followers):
            need = (reached | (self.stuck > 4.0)) & (self.v0 > 0) & ~going
            if need.any():
                self._new_goals(need, world, rng, robot_xy)
            return
        self._goals_and_pauses(dt, world, rng, robot_xy, reached, going, pausing)

    def _move(
        self,
        desired: FloatArray,
        dt: float,
        world: World,
        robot_xy: FloatArray,
        robot_radius: float,
        pausing: bool,
    ) -> None:
        """Move every agent by the social forces, never into walls or the robot; gait, stuck."""
        c = self.config
        pos, vel = self.pos, self.vel
        prm = np.array(
            [
                c.relaxation_time,
                c.person_strength,
                c.person_range,
                c.wall_strength,
                c.wall_range,
                c.robot_strength,
                c.robot_range,
            ]
        )
        force = social_forces(
            pos,
            vel,
            desired,
            self.radius,
            self.group,
            world.segments,
            world.circles,
            float(robot_xy[0]),
            float(robot_xy[1]),
            float(robot_radius),
            prm,
        )
        vel = vel + force * dt
        vmax = np.where(self.v0 > 0, 1.3 * self.v0, 0.4)
        if pausing:
            # a stopped walker only shuffles, like a standing one (when pushed or regrouping)
            vmax = np.where(self.paused, np.minimum(vmax, 0.3), vmax)
        sp = np.hypot(vel[:, 0], vel[:, 1])
        vel *= np.minimum(1.0, vmax / np.maximum(sp, 1e-9))[:, None]
        new = pos + vel * dt

        # hard constraints: never into walls (grid clearance), never into the robot
        ok = world.grid().clearance_at(new) >= 0.7 * self.radius
        new = np.where(ok[:, None], new, pos)
        vel = np.where(ok[:, None], vel, 0.0)
        dr = new - robot_xy
        ddr = np.hypot(dr[:, 0], dr[:, 1])
        inside = ddr < self.radius + robot_radius + 0.02
        if inside.any():
            push = (
                robot_xy
                + dr / np.maximum(ddr, 1e-6)[:, None] * (self.radius + robot_radius + 0.03)[:, None]
            )
            push_ok = world.grid().clearance_at(push) >= 0.7 * self.radius
            new = np.where((inside & push_ok)[:, None], push, new)
        moved = new - pos
        self.pos, self.vel = new, vel

        sp = np.hypot(vel[:, 0], vel[:, 1])
        walking = sp > 0.1
        self.heading = np.where(walking, np.arctan2(vel[:, 1], vel[:, 0]), self.heading)
        # gait: ~1 stride per 1.4 m walked
        self.phase = (self.phase + 2 * np.pi * np.hypot(moved[:, 0], moved[:, 1]) / 1.4) % (
            2 * np.pi
        )
        progress = np.hypot(moved[:, 0], moved[:, 1])
        self.stuck = np.where(progress < 0.2 * self.v0 * dt, self.stuck + dt, 0.0)

    def _goals_and_pauses(
        self,
        dt: float,
        world: World,
        rng: np.random.Generator,
        robot_xy: FloatArray,
        reached: NDArray[np.bool_],
        going: NDArray[np.bool_],
        pausing: bool,
    ) -> None:
        """New goals and pauses with the optional behaviours (pauses, followers) on."""
        c = self.config
        # stopped agents and followers keep their goals
        was_paused = self.paused
        self.stuck = np.where(was_paused | self.follow, 0.0, self.stuck)
        need = (reached | (self.stuck > 4.0)) & (self.v0 > 0) & ~was_paused & ~self.follow
        need &= ~going
        if need.any():
            self._new_goals(need, world, rng, robot_xy)
        if pausing:
            self.pause_left = np.maximum(self.pause_left - dt, 0.0)
            free = self._leaders() & ~self.follow & (self.v0 > 0) & ~was_paused & ~going
            start = np.zeros(self.n, dtype=bool)
            if c.pause_prob > 0:
                # stop on arrival (the next goal is already chosen: walk on after the stop)
                start |= free & reached & (rng.random(self.n) < c.pause_prob)
            if c.pause_rate > 0:
                # stop on the way: a Poisson process per walking agent
                start |= free & (rng.random(self.n) < c.pause_rate * dt)
            self._start_pauses(start, rng)

    # ------------------------------------------------------------------------------------

    def shapes(self) -> tuple[FloatArray, FloatArray]:
        """What the laser sees now: circles ``(M, 3)`` and segments ``(S, 4)`` (carts)."""
        c = self.config
        h = self.heading
        fwd = np.stack([np.cos(h), np.sin(h)], axis=1)
        side = np.stack([-fwd[:, 1], fwd[:, 0]], axis=1)
        legs = self.kind == LEGS
        sp = np.hypot(self.vel[:, 0], self.vel[:, 1])
        swing = (0.18 * np.minimum(sp / 1.2, 1.0) * np.sin(self.phase))[:, None]
        lp = self.pos[legs]
        left = lp + 0.1 * side[legs] + swing[legs] * fwd[legs]
        right = lp - 0.1 * side[legs] - swing[legs] * fwd[legs]
        r_leg = np.full(int(legs.sum()), c.leg_radius)
        body = self.kind == BODY
        circles = np.concatenate(
            [
                np.column_stack([left, r_leg]),
                np.column_stack([right, r_leg]),
                np.column_stack([self.pos[body], self.radius[body]]),
            ]
        )
        carts = np.nonzero(self.kind == CART)[0]
        segs = np.zeros((4 * carts.size, 4))
        hl, hw = _CART_SIZE[0] / 2, _CART_SIZE[1] / 2
        corners = np.array([(-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw)])
        for k, i in enumerate(carts):
            ca, sa = math.cos(h[i]), math.sin(h[i])
            pts = self.pos[i] + corners @ np.array([[ca, sa], [-sa, ca]])
            segs[4 * k : 4 * k + 4, :2] = pts
            segs[4 * k : 4 * k + 4, 2:] = np.roll(pts, -1, axis=0)
        return circles, segs
