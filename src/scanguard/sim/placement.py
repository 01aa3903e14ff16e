"""Where the simulator's people start and stand: spawn spots, followers' and gatherers' places.

Helpers of `scanguard.sim.people.Crowd`; every random draw is made in the order the crowd's
reproducibility relies on.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from scanguard.sim.config import PeopleConfig
from scanguard.sim.world import World

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


def place_agents(
    config: PeopleConfig,
    world: World,
    rng: np.random.Generator,
    robot_xy: FloatArray,
    robot_radius: float,
    radius: FloatArray,
    n_people: int,
) -> tuple[FloatArray, list[int], NDArray[np.bool_], FloatArray]:
    """Free, separate start spots for agents of radii ``radius`` (people first, then carts).

    Half of the agents start near the robot; the gatherers (the last ``gather_count``
    people) start away from where they will gather, in sight of it.

    Returns:
        The spots ``(N, 2)``, the agents placed (in order), the gatherers ``(N,)`` and the
        gathering place ``(2,)``.
    """
    n = len(radius)
    pos = np.zeros((n, 2))
    placed: list[int] = []
    pool = world.sample_free(rng, max(400, 30 * n), 0.65)
    near_idx = np.nonzero(np.hypot(*(pool - robot_xy).T) < 6.0)[0]
    # gatherers are the last people; they start away from where they will gather
    gather = np.zeros(n, dtype=bool)
    n_gather = min(config.gather_count, n_people)
    center = np.asarray(
        robot_xy if config.gather_point is None else config.gather_point, dtype=np.float64
    )
    far_idx = np.zeros(0, dtype=np.intp)
    if n_gather:
        gather[n_people - n_gather : n_people] = True
        far_idx = np.array(
            [
                k
                for k in np.nonzero(np.hypot(*(pool - center).T) > config.gather_spawn_distance)[0]
                if world.line_free(pool[k], center, 0.3)
            ],
            dtype=np.intp,
        )
    for i in range(n):
        # half of the agents start close to the robot so the first scans are crowded
        cands = near_idx if i < n // 2 and near_idx.size else np.arange(len(pool))
        if gather[i] and far_idx.size:
            cands = far_idx
        for idx in rng.permutation(cands)[:200]:
            p = pool[idx]
            if np.hypot(*(p - robot_xy)) < robot_radius + radius[i] + 0.5:
                continue
            if world.grid().clearance_at(p[None])[0] < radius[i] + 0.05:
                continue
            if all(np.hypot(*(p - pos[j])) > radius[i] + radius[j] + 0.1 for j in placed):
                pos[i] = p
                placed.append(i)
                break
    return pos, placed, gather, center


def place_followers(
    pos: FloatArray,
    radius: FloatArray,
    follow: NDArray[np.bool_],
    offset: FloatArray,
    world: World,
    robot_xy: FloatArray,
    heading: float,
    robot_radius: float,
) -> FloatArray:
    """Move followers to their places beside the robot where those are free (else keep)."""
    out = pos.copy()
    ch, sh = math.cos(heading), math.sin(heading)
    for i in np.nonzero(follow)[0]:
        p = robot_xy + np.array(
            [ch * offset[i, 0] - sh * offset[i, 1], sh * offset[i, 0] + ch * offset[i, 1]]
        )
        if world.grid().clearance_at(p[None])[0] < radius[i] + 0.05:
            continue
        if math.dist(p, robot_xy) < robot_radius + radius[i] + 0.1:
            continue
        d = np.hypot(*(out - p).T)
        d[i] = np.inf
        if np.all(d > radius + radius[i] + 0.1):
            out[i] = p
    return out


def route_distance(points: FloatArray, route: FloatArray) -> FloatArray:
    """Distance of points ``(N, 2)`` to the polyline ``route`` ``(K, 2)`` (inf without one)."""
    if len(route) < 2:
        return np.full(len(points), np.inf)
    a, b = route[:-1], route[1:]
    ab = b - a
    ap = points[:, None, :] - a[None, :, :]
    t = np.clip(np.sum(ap * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=1), 1e-12), 0.0, 1.0)
    d = ap - t[:, :, None] * ab[None, :, :]
    return np.asarray(np.min(np.hypot(d[..., 0], d[..., 1]), axis=1), dtype=np.float64)


def gather_spots(
    config: PeopleConfig,
    world: World,
    rng: np.random.Generator,
    center: FloatArray,
    radius: FloatArray,
    gather: NDArray[np.bool_],
    route: FloatArray,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Standing spots near ``center`` for the ``gather`` agents, clear of each other.

    Returns:
        The spots ``(N, 2)`` and the agents that got one (a subset of ``gather``).
    """
    spots = np.zeros((len(radius), 2))
    got = np.zeros(len(radius), dtype=bool)
    for i in np.nonzero(gather)[0]:
        r = config.gather_radius * np.sqrt(rng.random(200))
        phi = rng.uniform(-np.pi, np.pi, size=200)
        cand = center + np.column_stack([r * np.cos(phi), r * np.sin(phi)])
        ok = world.is_free(cand, float(radius[i]) + 0.1)
        ok &= route_distance(cand, route) >= config.gather_lane
        for j in np.nonzero(got)[0]:
            ok &= np.hypot(*(cand - spots[j]).T) > radius[i] + radius[j] + 0.1
        if ok.any():
            spots[i] = cand[int(np.argmax(ok))]
            got[i] = True
    if got.sum() < gather.sum():
        log.warning("only %d of %d gathering people fit near %s", int(got.sum()),
                    int(gather.sum()), np.round(center, 2).tolist())  # fmt: skip
    return spots, got
