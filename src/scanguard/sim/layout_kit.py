"""Drawing tools of the built-in world layouts (`scanguard.sim.worldgen`): walls, boxes, pillars.

Every random draw is made in the order the layouts' reproducibility relies on.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import NDArray

from scanguard.sim.config import sample_param
from scanguard.sim.world import GLASS, NORMAL

#: Parameters of a generator: a value, or a ``(low, high)`` range to draw it from.
Params = dict[str, float | tuple[float, float]]


class Builder:
    """The geometry a generator draws: wall segments, circles, their materials, a route."""

    def __init__(self) -> None:
        self.segs: list[tuple[float, float, float, float]] = []
        self.mats: list[int] = []
        self.circles: list[tuple[float, float, float]] = []
        self.cmats: list[int] = []
        #: Suggested robot route (waypoints after the start); only some generators set it.
        self.route: list[tuple[float, float]] = []
        self.info: dict[str, float] = {}

    def polyline(
        self, pts: list[tuple[float, float]], material: int = NORMAL, closed: bool = False
    ) -> None:
        """Walls along ``pts`` (closed: back to the first point); repeated points are skipped."""
        p = list(pts) + ([pts[0]] if closed else [])
        for (x0, y0), (x1, y1) in itertools.pairwise(p):
            if (x0, y0) != (x1, y1):
                self.segs.append((float(x0), float(y0), float(x1), float(y1)))
                self.mats.append(material)

    def box(
        self, cx: float, cy: float, w: float, h: float, angle: float = 0.0, material: int = NORMAL
    ) -> None:
        """A ``w`` x ``h`` rectangle centred at ``(cx, cy)``, turned by ``angle`` (rad)."""
        c, s = math.cos(angle), math.sin(angle)
        corners = [(-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)]
        pts = [(cx + c * x - s * y, cy + s * x + c * y) for x, y in corners]
        self.polyline(pts, material, closed=True)

    def circle(self, cx: float, cy: float, r: float, material: int = NORMAL) -> None:
        """A round pillar."""
        self.circles.append((float(cx), float(cy), float(r)))
        self.cmats.append(material)


def place_points(
    rng: np.random.Generator,
    n: int,
    lo: tuple[float, float],
    hi: tuple[float, float],
    min_dist: float,
    taken: list[tuple[float, float]],
) -> list[tuple[float, float]]:
    """Up to ``n`` random points in a box, at least ``min_dist`` from each other and ``taken``."""
    out: list[tuple[float, float]] = []
    for _ in range(n * 40):
        if len(out) >= n:
            break
        p = (float(rng.uniform(lo[0], hi[0])), float(rng.uniform(lo[1], hi[1])))
        if all(math.dist(p, q) >= min_dist for q in taken + out):
            out.append(p)
    return out


def wall_with_recesses(
    b: Builder,
    rng: np.random.Generator,
    x0: float,
    x1: float,
    y: float,
    outward: float,
    n: int,
    width: tuple[float, float],
    depth: tuple[float, float],
    material: int = NORMAL,
) -> None:
    """A wall along x at ``y`` with ``n`` rectangular recesses pushed ``outward`` (±1)."""
    spots = sorted(place_points(rng, n, (x0 + 2.0, 0.0), (x1 - 2.0, 0.0), max(width) + 1.0, []))
    pts: list[tuple[float, float]] = [(x0, y)]
    for cx, _ in spots:
        w, d = rng.uniform(*width), rng.uniform(*depth)
        pts += [(cx - w / 2, y), (cx - w / 2, y + outward * d)]
        pts += [(cx + w / 2, y + outward * d), (cx + w / 2, y)]
    pts.append((x1, y))
    b.polyline(pts, material)


def param(
    params: Params,
    key: str,
    default: float | tuple[float, float],
    rng: np.random.Generator,
) -> float:
    """Parameter ``key`` of a generator (a value, or a range to draw from), else ``default``."""
    return sample_param(params.get(key, default), rng)


def line_with_pieces(
    b: Builder,
    p0: tuple[float, float],
    p1: tuple[float, float],
    pieces: list[tuple[float, float, int]],
) -> None:
    """A straight wall p0→p1 with pieces of other materials and gaps.

    ``pieces`` are ``(from, to, material)`` intervals in metres along the wall (disjoint) that
    replace the normal wall there; material ``-1`` is a gap (a door).
    """
    length = math.dist(p0, p1)
    ux, uy = (p1[0] - p0[0]) / length, (p1[1] - p0[1]) / length

    def at(t: float) -> tuple[float, float]:
        return (p0[0] + ux * t, p0[1] + uy * t)

    t = 0.0
    for t0, t1, mat in sorted(pieces):
        t0, t1 = max(t0, t), min(t1, length)
        if t1 <= t0:
            continue
        if t0 > t:
            b.polyline([at(t), at(t0)])
        if mat >= 0:
            b.polyline([at(t0), at(t1)], mat)
        t = t1
    if t < length:
        b.polyline([at(t), at(length)])


def glass_panes(length: float, pitch: float = 2.5) -> list[tuple[float, float, int]]:
    """Glass panes between 0.2 m mullions along a wall of ``length`` metres."""
    edges = np.linspace(0.0, length, max(1, round(length / pitch)) + 1)
    return [(float(a) + 0.1, float(c) - 0.1, GLASS) for a, c in itertools.pairwise(edges)]


def rect_route(
    rng: np.random.Generator, hx: float, hy: float
) -> tuple[tuple[float, float, float], list[tuple[float, float]]]:
    """A rectangular loop ``|x| = hx, |y| = hy`` from the middle of its south side, either way."""
    x0 = float(rng.uniform(-0.2, 0.2) * hx)
    corners = [(hx, -hy), (hx, hy), (-hx, hy), (-hx, -hy)]
    if rng.random() < 0.5:
        return (x0, -hy, 0.0), [*corners, (x0, -hy)]
    return (x0, -hy, math.pi), [*corners[::-1], (x0, -hy)]


def door_pieces(
    rng: np.random.Generator, edges: NDArray[np.float64], door: float, open_prob: float
) -> list[tuple[float, float, int]]:
    """One door per room between consecutive ``edges`` (an open front with ``open_prob``)."""
    out: list[tuple[float, float, int]] = []
    for a, c in itertools.pairwise(edges):
        if rng.random() < open_prob and c - a > 2.0:
            out.append((float(a) + 0.5, float(c) - 0.5, -1))  # a lounge, open to the corridor
        else:
            t = float(rng.uniform(a + 0.4, max(c - 0.4 - door, a + 0.4)))
            out.append((t, t + door, -1))
    return out


def periodic_wall(
    b: Builder,
    x0: float,
    x1: float,
    y: float,
    period: float,
    n: int,
    offset: float,
    width: float,
    depth: float,
) -> None:
    """A wall along x at ``y`` from ``x0`` to ``x1`` with a door recess every ``period`` m.

    The recesses start ``offset`` m into each of the ``n`` periods that begin at x = 0 and go
    ``depth`` m towards -y (or +y for a negative ``depth``).
    """
    pts: list[tuple[float, float]] = [(x0, y)]
    for k in range(n):
        a = k * period + offset
        pts += [(a, y), (a, y - depth), (a + width, y - depth), (a + width, y)]
    pts.append((x1, y))
    b.polyline(pts)
