"""World generators: built-in random floor plans and `build_world`.

Built-in generators produce a different random floor plan per seed (a model must not be able to
memorise one layout); explicit YAML walls/circles are added on top (or used alone). Each
generator draws on a `scanguard.sim.layout_kit.Builder` and returns the suggested robot start.
"""

from __future__ import annotations

import itertools
import logging
import math

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import ConfigError
from scanguard.sim.config import WorldConfig
from scanguard.sim.layout_kit import (
    Builder,
    Params,
    door_pieces,
    glass_panes,
    line_with_pieces,
    param,
    periodic_wall,
    place_points,
    rect_route,
    wall_with_recesses,
)
from scanguard.sim.world import GLASS, MATERIALS, MAX_PRIMITIVES, MIRROR, NORMAL, World, nav_grid

log = logging.getLogger(__name__)


def _gen_lobby(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    W, D = param(prm, "width", (18.0, 26.0), rng), param(prm, "depth", (12.0, 18.0), rng)
    w, d = W / 2, D / 2
    wall_with_recesses(b, rng, -w, w, -d, -1.0, 3, (1.2, 3.0), (0.4, 1.5))
    wall_with_recesses(b, rng, -w, w, d, 1.0, 3, (1.2, 3.0), (0.4, 1.5))
    b.polyline([(w, -d), (w, d)])
    b.polyline([(-w, -d), (-w, d)])
    # partition fins sticking out of the side walls: strong corners for the scan matcher
    for side in (-1.0, 1.0):
        for y in rng.uniform(-d + 2, d - 2, size=int(param(prm, "fins", (1, 3), rng))):
            b.polyline([(side * w, y), (side * (w - rng.uniform(1.0, 2.5)), y)])
    taken: list[tuple[float, float]] = [(0.0, 0.0)]
    n_pil = round(param(prm, "pillars", (4, 8), rng))
    for cx, cy in place_points(rng, n_pil, (-w + 2.5, -d + 2.5), (w - 2.5, d - 2.5), 3.0, taken):
        if rng.random() < 0.5:
            b.circle(cx, cy, rng.uniform(0.25, 0.5))
        else:
            s = rng.uniform(0.5, 0.9)
            b.box(cx, cy, s, s, rng.uniform(0, np.pi / 2))
        taken.append((cx, cy))
    # reception desk and a few benches/planters
    for cx, cy in place_points(rng, 1, (-w + 3, -d + 3), (w - 3, d - 3), 3.5, taken):
        b.box(cx, cy, rng.uniform(2.0, 3.5), rng.uniform(0.6, 1.0), rng.choice([0.0, np.pi / 2]))
        taken.append((cx, cy))
    for cx, cy in place_points(rng, int(param(prm, "benches", (2, 5), rng)), (-w + 1.5, -d + 1.5),
                         (w - 1.5, d - 1.5), 2.5, taken):  # fmt: skip
        b.box(cx, cy, rng.uniform(1.0, 1.8), 0.45, rng.uniform(0, np.pi))
        taken.append((cx, cy))
    return (0.0, 0.0, float(rng.uniform(-np.pi, np.pi)))


def _gen_corridor(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    L, Wd = param(prm, "length", (44.0, 64.0), rng), param(prm, "width", (2.0, 3.0), rng)
    half, hw = L / 2, Wd / 2
    n_rec = round(param(prm, "recesses", (0, 2), rng))
    # door recesses are shallow: few features along the axis is the point of this world
    wall_with_recesses(b, rng, -half, half, -hw, -1.0, n_rec, (0.9, 1.2), (0.08, 0.15))
    wall_with_recesses(b, rng, -half, half, hw, 1.0, n_rec, (0.9, 1.2), (0.08, 0.15))
    b.polyline([(-half, -hw), (-half, hw)])
    b.polyline([(half, -hw), (half, hw)])
    x = float(rng.uniform(-half / 2, half / 2))
    return (x, float(rng.uniform(-0.2, 0.2)), float(rng.choice([0.0, np.pi])))


def _gen_glass(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    W, D = param(prm, "width", (16.0, 24.0), rng), param(prm, "depth", (10.0, 14.0), rng)
    w, d = W / 2, D / 2
    # south façade: glass panes between thin mullions, open space and a far building behind
    xs = np.linspace(-w, w, int(W // 2.5) + 1)
    for x0, x1 in itertools.pairwise(xs):
        b.polyline([(x0 + 0.1, -d), (x1 - 0.1, -d)], GLASS)
        b.polyline([(x1 - 0.1, -d), (x1 + 0.1, -d)])
    b.polyline([(-w, -d), (-w + 0.1, -d)])
    far = d + param(prm, "outside_depth", (4.0, 10.0), rng)
    b.polyline([(-w - 6, -d), (-w - 6, -far), (w + 6, -far), (w + 6, -d), (w, -d)])
    b.polyline([(-w - 6, -d), (-w, -d)])
    for cx in rng.uniform(-w, w, size=int(param(prm, "trees", (3, 7), rng))):
        b.circle(cx, float(rng.uniform(-far + 1.0, -d - 1.0)), rng.uniform(0.15, 0.4))
    # north wall: lift doors are polished steel — mirrors
    n_lift = round(param(prm, "lifts", (2, 4), rng))
    lifts = sorted(place_points(rng, n_lift, (-w + 2.0, 0.0), (w - 2.0, 0.0), 2.5, []))
    pts: list[tuple[float, float]] = [(-w, d)]
    for cx, _ in lifts:
        lw = rng.uniform(1.0, 1.6)
        pts += [(cx - lw / 2 - 0.3, d), (cx - lw / 2 - 0.3, d - 0.25), (cx - lw / 2, d - 0.25)]
        b.polyline(pts)
        b.polyline([(cx - lw / 2, d - 0.25), (cx + lw / 2, d - 0.25)], MIRROR)
        pts = [(cx + lw / 2, d - 0.25), (cx + lw / 2 + 0.3, d - 0.25), (cx + lw / 2 + 0.3, d)]
    pts.append((w, d))
    b.polyline(pts)
    # east wall with a big mirror panel, west wall with windows
    ym = float(rng.uniform(-d + 2.5, d - 4.5))
    mlen = float(rng.uniform(2.0, 4.0))
    b.polyline([(w, -d), (w, ym)])
    b.polyline([(w, ym), (w, ym + mlen)], MIRROR)
    b.polyline([(w, ym + mlen), (w, d)])
    yw = float(rng.uniform(-d + 1.5, d - 4.5))
    b.polyline([(-w, -d), (-w, yw)])
    b.polyline([(-w, yw), (-w, yw + 3.0)], GLASS)
    b.polyline([(-w, yw + 3.0), (-w, d)])
    b.polyline([(-w, yw), (-w - 3, yw), (-w - 3, yw + 3), (-w, yw + 3)])
    taken: list[tuple[float, float]] = [(0.0, 0.0)]
    for cx, cy in place_points(rng, int(param(prm, "pillars", (2, 4), rng)), (-w + 2.5, -d + 2.5),
                         (w - 2.5, d - 2.5), 3.0, taken):  # fmt: skip
        s = rng.uniform(0.5, 0.8)
        # some pillars are clad in mirror panels, as in many lobbies
        b.box(cx, cy, s, s, 0.0, MIRROR if rng.random() < 0.4 else NORMAL)
        taken.append((cx, cy))
    return (0.0, 0.0, float(rng.uniform(-np.pi, np.pi)))


def _gen_hall(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    W, D = param(prm, "width", (60.0, 80.0), rng), param(prm, "depth", (40.0, 52.0), rng)
    w, d = W / 2, D / 2
    b.polyline([(-w, -d), (w, -d), (w, d), (-w, d)], closed=True)
    taken: list[tuple[float, float]] = [(0.0, 0.0)]
    # sparse pillar grid: the only structure within range for much of the hall
    pitch = param(prm, "pillar_pitch", (9.0, 14.0), rng)
    gx = np.arange(-w + pitch / 2, w, pitch)
    gy = np.arange(-d + pitch / 2, d, pitch)
    for cx in gx:
        for cy in gy:
            if rng.random() < param(prm, "pillar_prob", 0.7, rng) and math.hypot(cx, cy) > 2.0:
                b.circle(cx, cy, rng.uniform(0.3, 0.5))
                taken.append((cx, cy))
    for cx, cy in place_points(rng, int(param(prm, "kiosks", (2, 5), rng)), (-w + 4, -d + 4),
                         (w - 4, d - 4), 6.0, taken):  # fmt: skip
        b.box(cx, cy, rng.uniform(1.5, 3.0), rng.uniform(1.0, 2.0), rng.uniform(0, np.pi))
    return (float(rng.uniform(-w / 3, w / 3)), float(rng.uniform(-d / 3, d / 3)),
            float(rng.uniform(-np.pi, np.pi)))  # fmt: skip


def _gen_office(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    W, D = param(prm, "width", (22.0, 30.0), rng), param(prm, "depth", (14.0, 18.0), rng)
    w, d = W / 2, D / 2
    cw = param(prm, "corridor_width", (2.0, 2.6), rng) / 2
    b.polyline([(-w, -d), (w, -d), (w, d), (-w, d)], closed=True)
    n_rooms = round(param(prm, "rooms_per_side", (3, 5), rng))
    xs = np.linspace(-w, w, n_rooms + 1)
    for side in (-1.0, 1.0):
        yc = side * cw
        pts: list[tuple[float, float]] = [(-w, yc)]
        for x0, x1 in itertools.pairwise(xs):
            door = float(rng.uniform(x0 + 0.5, x1 - 1.5))
            pts.append((door, yc))
            b.polyline(pts)
            pts = [(door + 1.0, yc)]
            if x1 < w - 1e-6:
                b.polyline([(x1, yc), (x1, side * d)])
            # desks and cabinets: the office clutter that hides the structure
            for _ in range(int(rng.integers(1, 4))):
                cx = float(rng.uniform(x0 + 1.0, x1 - 1.0))
                cy = side * float(rng.uniform(cw + 1.8, d - 0.8))
                b.box(cx, cy, rng.uniform(0.8, 1.6), rng.uniform(0.5, 0.8), rng.choice([0.0, 1.57]))
        pts.append((w, yc))
        b.polyline(pts)
    return (float(rng.uniform(-w / 2, w / 2)), 0.0, float(rng.choice([0.0, np.pi])))


# --- generators with a suggested loop route (for the GMapping trap scenarios) ---------------


def _gen_atrium(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    """A hall around a central block (a lobby's core): the robot laps the ring between them.

    Params: ``width``, ``depth`` (hall), ``ring`` (hall wall to block), ``pillars``,
    ``benches``, ``niches`` (door recesses per long wall), ``glass_sides`` (0-2 glass façades,
    south first, with a building ``outside_depth`` m behind), ``block_glass`` (probability
    that a face of the block is a shop window with shelves behind it), ``mirrors`` (mirror
    panels on the block and the east/west walls), ``mirror_pillars`` (probability).
    """
    W, D = param(prm, "width", (20.0, 26.0), rng), param(prm, "depth", (14.0, 18.0), rng)
    ring = param(prm, "ring", (4.5, 6.0), rng)
    w, d = W / 2, D / 2
    bw, bd = w - ring, d - ring  # half sizes of the central block
    if bw < 0.5 or bd < 0.5:
        raise ConfigError(f"atrium: ring {ring:.1f} m leaves no central block in {W:.1f} x {D:.1f}")
    _atrium_long_walls(b, rng, prm, w, d)
    _atrium_faces(b, rng, prm, (w, d), (bw, bd))
    _atrium_furniture(b, rng, prm, (w, d), (bw, bd), ring)
    start, b.route = rect_route(rng, w - ring / 2, d - ring / 2)
    b.info.update(width=W, depth=D, ring=ring)
    return start


def _atrium_long_walls(
    b: Builder,
    rng: np.random.Generator,
    prm: Params,
    w: float,
    d: float,
) -> None:
    """The atrium's long walls: glass façades (a far building behind them) or door niches."""
    n_glass = round(param(prm, "glass_sides", 0.0, rng))
    for side, y in ((-1.0, -d), (1.0, d)):
        glass = n_glass >= (1 if side < 0 else 2)
        if glass:
            line_with_pieces(b, (-w, y), (w, y), glass_panes(2 * w))
            far = y + side * param(prm, "outside_depth", (4.0, 10.0), rng)
            b.polyline([(-w, y), (-w - 4, y), (-w - 4, far), (w + 4, far), (w + 4, y), (w, y)])
            for cx in rng.uniform(-w, w, size=int(param(prm, "trees", (2, 5), rng))):
                b.circle(cx, float(rng.uniform(min(y, far) + 1.0, max(y, far) - 1.0)),
                         rng.uniform(0.15, 0.4))  # fmt: skip
        else:
            n_niche = round(param(prm, "niches", (1, 3), rng))
            wall_with_recesses(b, rng, -w, w, y, side, n_niche, (1.0, 2.0), (0.3, 0.8))


def _atrium_faces(
    b: Builder,
    rng: np.random.Generator,
    prm: Params,
    half: tuple[float, float],
    block: tuple[float, float],
) -> None:
    """The east/west walls and the block's faces: shop windows (shelves behind), mirrors."""
    (w, d), (bw, bd) = half, block
    n_mirror = round(param(prm, "mirrors", 0.0, rng))
    faces: list[tuple[tuple[float, float], tuple[float, float]]] = [
        ((-w, -d), (-w, d)),  # west wall
        ((w, -d), (w, d)),  # east wall
        ((-bw, -bd), (bw, -bd)),  # block: south, north, west, east faces
        ((-bw, bd), (bw, bd)),
        ((-bw, -bd), (-bw, bd)),
        ((bw, -bd), (bw, bd)),
    ]
    pieces: list[list[tuple[float, float, int]]] = [[] for _ in faces]
    shop_glass = param(prm, "block_glass", 0.0, rng)
    for k in range(2, 6):
        if rng.random() < shop_glass:
            pieces[k] = glass_panes(math.dist(*faces[k]))
    # mirror panels (polished lift doors, mirror walls) on the non-glass faces
    for _ in range(n_mirror):
        k = int(rng.integers(0, len(faces)))
        length = math.dist(*faces[k])
        if any(m == GLASS for _, _, m in pieces[k]) or length < 2.0:
            continue
        pw = float(rng.uniform(1.0, min(3.0, length - 0.6)))
        t0 = float(rng.uniform(0.3, length - pw - 0.3))
        if all(t0 + pw < a - 0.2 or t0 > c + 0.2 for a, c, _ in pieces[k]):
            pieces[k].append((t0, t0 + pw, MIRROR))
    for (p0, p1), pc in zip(faces, pieces, strict=True):
        line_with_pieces(b, p0, p1, pc)
    # shelves inside a glass block face: seen through the shop window
    for k in range(2, 6):
        if pieces[k] and pieces[k][0][2] == GLASS:
            (x0, y0), (x1, y1) = faces[k]
            mx, my = (x0 + x1) / 2, (y0 + y1) / 2
            inward = (-math.copysign(1.0, mx) if k >= 4 else 0.0,
                      -math.copysign(1.0, my) if k < 4 else 0.0)  # fmt: skip
            depth = min(bw, bd) * 0.5
            for t in np.linspace(0.2, 0.8, 3):
                cx = x0 + (x1 - x0) * t + inward[0] * depth
                cy = y0 + (y1 - y0) * t + inward[1] * depth
                b.box(cx, cy, 0.8 if k < 4 else 0.4, 0.4 if k < 4 else 0.8)


def _atrium_furniture(
    b: Builder,
    rng: np.random.Generator,
    prm: Params,
    half: tuple[float, float],
    block: tuple[float, float],
    ring: float,
) -> None:
    """Pillars and benches near the hall walls and the block, clear of the robot's lane."""
    (w, d), (bw, bd) = half, block
    # pillars and benches near the walls and the block, leaving >= 1 m between them and the
    # robot's lane (a person must fit through, or the robot pins people against them)
    taken: list[tuple[float, float]] = []
    p_mirror = param(prm, "mirror_pillars", 0.0, rng)
    band = max(ring / 2 - 1.7, 0.6)
    for kind, n in (("pillar", round(param(prm, "pillars", (4, 8), rng))),
                    ("bench", round(param(prm, "benches", (2, 4), rng)))):  # fmt: skip
        for _ in range(n * 20):
            if n <= 0:
                break
            # a random spot 0.5..band m inside the hall walls, or outside the block
            outer = rng.random() < 0.6
            hx, hy = (w, d) if outer else (bw, bd)
            off = float(rng.uniform(0.5, band)) * (-1.0 if outer else 1.0)
            if rng.random() < hx / (hx + hy):
                x, y = float(rng.uniform(-hx + 1.0, hx - 1.0)), float(rng.choice([-1.0, 1.0]))
                cx, cy, along_x = x, y * (hy + off), True
            else:
                y, x = float(rng.uniform(-hy + 1.0, hy - 1.0)), float(rng.choice([-1.0, 1.0]))
                cx, cy, along_x = x * (hx + off), y, False
            if any(math.dist((cx, cy), q) < 2.0 for q in taken):
                continue
            taken.append((cx, cy))
            n -= 1
            if kind == "bench":
                b.box(cx, cy, 1.4 if along_x else 0.45, 0.45 if along_x else 1.4)
            elif rng.random() < p_mirror:
                s = float(rng.uniform(0.5, 0.7))
                b.box(cx, cy, s, s, 0.0, MIRROR)
            else:
                b.circle(cx, cy, float(rng.uniform(0.2, 0.35)))


def _gen_long_corridor(
    b: Builder, rng: np.random.Generator, prm: Params
) -> tuple[float, float, float]:
    """A long plain corridor between two small end halls; the route goes end to end and back.

    Params: ``length``, ``width``, ``doors`` (shallow door recesses per side), ``end_length``,
    ``end_width`` (the end halls, the only places with structure).
    """
    L, Wd = param(prm, "length", (60.0, 70.0), rng), param(prm, "width", 2.5, rng)
    el, ew = param(prm, "end_length", 4.0, rng), param(prm, "end_width", 5.0, rng)
    half, hw = L / 2, Wd / 2
    n_doors = round(param(prm, "doors", (1, 3), rng))
    # parallel walls with a few flush doors (2-3 cm recesses): almost no along-axis structure
    wall_with_recesses(b, rng, -half, half, -hw, -1.0, n_doors, (0.9, 1.1), (0.02, 0.04))
    wall_with_recesses(b, rng, -half, half, hw, 1.0, n_doors, (0.9, 1.1), (0.02, 0.04))
    for sx in (-1.0, 1.0):
        x0, x1 = sx * half, sx * (half + el)
        b.polyline([(x0, hw), (x0, ew / 2), (x1, ew / 2), (x1, -ew / 2), (x0, -ew / 2), (x0, -hw)])
        # a cabinet and a pillar in each end hall, off the axis the robot drives on
        cy = float(rng.choice([-1.0, 1.0]))
        b.box(x0 + sx * el / 2, cy * (ew / 2 - 0.4), rng.uniform(0.8, 1.4), 0.5)
        b.circle(x0 + sx * rng.uniform(0.6, el - 0.6), -cy * (ew / 2 - 0.5), 0.2)
    xs = half + el / 2
    b.route = [(xs, 0.0), (-xs, 0.0)]
    b.info.update(length=L, width=Wd)
    return (-xs, 0.0, 0.0)


def _gen_building(b: Builder, rng: np.random.Generator, prm: Params) -> tuple[float, float, float]:
    """An office floor: a corridor loop between outer rooms and a core of rooms (with doors).

    Params: ``width``, ``depth`` (building), ``room_depth`` (outer rooms), ``corridor_width``,
    ``room_width``, ``door`` (door width), ``open_prob`` (a room is an open lounge).
    """
    W, D = param(prm, "width", (26.0, 34.0), rng), param(prm, "depth", (18.0, 22.0), rng)
    R, C = param(prm, "room_depth", (4.0, 4.5), rng), param(prm, "corridor_width", (2.2, 2.6), rng)
    rw, door = param(prm, "room_width", (3.5, 5.0), rng), param(prm, "door", 1.0, rng)
    open_prob = param(prm, "open_prob", 0.15, rng)
    w, d = W / 2, D / 2
    cw, cd = w - R - C, d - R - C  # half sizes of the core
    if cw < 1.0 or cd < 1.0:
        raise ConfigError(f"building: {W:.1f} x {D:.1f} m leaves no core for rooms of {R:.1f} m")
    b.polyline([(-w, -d), (w, -d), (w, d), (-w, d)], closed=True)

    def edges(length: float) -> NDArray[np.float64]:
        return np.linspace(0.0, length, max(1, round(length / rw)) + 1)

    # outer rooms: a band along each wall, doors onto the corridor, partitions between rooms
    for (p0, p1), out in (
        (((-w + R, -d + R), (w - R, -d + R)), (0.0, -1.0)),
        (((-w + R, d - R), (w - R, d - R)), (0.0, 1.0)),
        (((-w + R, -d + R), (-w + R, d - R)), (-1.0, 0.0)),
        (((w - R, -d + R), (w - R, d - R)), (1.0, 0.0)),
    ):
        length = math.dist(p0, p1)
        e = edges(length)
        line_with_pieces(b, p0, p1, door_pieces(rng, e, door, open_prob))
        ux, uy = (p1[0] - p0[0]) / length, (p1[1] - p0[1]) / length
        for t in e:
            x, y = p0[0] + ux * t, p0[1] + uy * t
            b.polyline([(x, y), (x + out[0] * R, y + out[1] * R)])
        for a, c in itertools.pairwise(e):
            if rng.random() < 0.7:  # a desk against the outer wall
                t = float(rng.uniform(a + 1.0, max(c - 1.0, a + 1.0)))
                x, y = p0[0] + ux * t + out[0] * (R - 0.6), p0[1] + uy * t + out[1] * (R - 0.6)
                along = abs(ux) > 0.5
                b.box(x, y, 1.2 if along else 0.7, 0.7 if along else 1.2)
    # the core: rooms across its depth, doors on the south or north face
    e = edges(2 * cw)
    doors = door_pieces(rng, e, door, 0.0)
    south = rng.random(len(doors)) < 0.5
    line_with_pieces(b, (-cw, -cd), (cw, -cd), [p for p, s in zip(doors, south, strict=True) if s])
    line_with_pieces(b, (-cw, cd), (cw, cd), [p for p, s in zip(doors, south, strict=True)
                                               if not s])  # fmt: skip
    for t in e:
        b.polyline([(-cw + t, -cd), (-cw + t, cd)])
    start, b.route = rect_route(rng, w - R - C / 2, d - R - C / 2)
    b.info.update(width=W, depth=D, room_depth=R, corridor_width=C)
    return start


# --- loop-closure traps: perceptual aliasing --------------------------------------------------


def _gen_twin_rooms(
    b: Builder, rng: np.random.Generator, prm: Params
) -> tuple[float, float, float]:
    """Identical rooms side by side inside a corridor loop (perceptual aliasing).

    Every room has the same size, the same door in its south wall and the same furniture, so
    a scan taken in one room matches the scan at the same place in the next room, shifted by
    ``room_width`` along x (``info["twin_dx"]``). The route goes round the corridor loop and
    drives the same circuit through each room.

    Params: ``rooms`` (how many twins), ``room_width``, ``room_depth``, ``corridor_width``
    (the corridor loop around the rooms), ``door`` (door width).
    """
    n = round(param(prm, "rooms", 2.0, rng))
    W, D = param(prm, "room_width", (3.8, 4.4), rng), param(prm, "room_depth", (4.8, 5.4), rng)
    C, door = param(prm, "corridor_width", (2.0, 2.4), rng), param(prm, "door", 1.1, rng)
    if door > W - 1.2:
        raise ConfigError(f"twin_rooms: a door of {door:.1f} m does not fit a {W:.1f} m room")
    # one layout for all rooms, in room coordinates (origin at the room's south-west corner)
    xd = float(rng.uniform(0.6 + door / 2, W - 0.6 - door / 2))  # door centre
    west = xd < W / 2  # the door is in the west half: the circuit turns east inside
    xo = W - 1.0 if west else 1.0
    desk = (float(rng.uniform(1.0, W - 1.0)), D - 0.4, float(rng.uniform(1.2, 1.6)), 0.6)
    cab_x = 0.3 if rng.random() < 0.5 else W - 0.3
    cabinet = (cab_x, float(rng.uniform(1.8, D - 2.2)), 0.5, 1.0)
    plant = (W - 0.45 if west else 0.45, 0.45, float(rng.uniform(0.2, 0.28)))
    nw = n * W
    # the rooms: one block with a door per room in its south face and partitions between rooms
    doors = [(k * W + xd - door / 2, k * W + xd + door / 2, -1) for k in range(n)]
    line_with_pieces(b, (0.0, 0.0), (nw, 0.0), doors)
    b.polyline([(nw, 0.0), (nw, D), (0.0, D), (0.0, 0.0)])
    for k in range(1, n):
        b.polyline([(k * W, 0.0), (k * W, D)])
    for k in range(n):
        x0 = k * W
        b.box(x0 + desk[0], desk[1], desk[2], desk[3])
        b.box(x0 + cabinet[0], cabinet[1], cabinet[2], cabinet[3])
        b.circle(x0 + plant[0], plant[1], plant[2])
    # the corridor loop around them: a few niches in its outer walls (different everywhere)
    wall_with_recesses(b, rng, -C, nw + C, -C, -1.0, 2, (1.0, 1.6), (0.2, 0.5))
    wall_with_recesses(b, rng, -C, nw + C, D + C, 1.0, 2, (1.0, 1.6), (0.2, 0.5))
    b.polyline([(-C, -C), (-C, D + C)])
    b.polyline([(nw + C, -C), (nw + C, D + C)])
    yc = -C / 2
    route: list[tuple[float, float]] = [(-C / 2, yc)]
    for k in range(n):
        x0 = k * W
        # in through the door, north, across, back south and out through the same door
        route += [(x0 + xd, yc), (x0 + xd, 0.9), (x0 + xd, D - 1.6), (x0 + xo, D - 1.6)]
        route += [(x0 + xo, 1.3), (x0 + xd, 0.9), (x0 + xd, yc)]
    route += [(nw + C / 2, yc), (nw + C / 2, D + C / 2), (-C / 2, D + C / 2), (-C / 2, D / 2)]
    b.route = route
    b.info.update(rooms=n, room_width=W, room_depth=D, corridor_width=C, door_x=xd,
                  twin_dx=W, twin_dy=0.0)  # fmt: skip
    return (-C / 2, D / 2, -math.pi / 2)


def _gen_twin_corridors(
    b: Builder, rng: np.random.Generator, prm: Params
) -> tuple[float, float, float]:
    """Two identical, periodic parallel corridors joined at their ends into a loop.

    Each long corridor has a door recess and a pilaster every ``period`` m (the same in
    every period), and the north corridor is the south one shifted by ``separation`` m along
    y (``info["twin_dy"]``): a scan is matched as well one period along the corridor, or in
    the other corridor, as at its true place. The route laps the loop counter-clockwise, then
    clockwise, so the second lap drives the south corridor in the direction the first drove
    the north one.

    Params: ``period``, ``periods`` (periods per corridor), ``corridor_width``,
    ``separation`` (between the corridors' centre lines).
    """
    P, n = param(prm, "period", (2.6, 3.0), rng), round(param(prm, "periods", 8.0, rng))
    C, H = param(prm, "corridor_width", (2.0, 2.4), rng), param(prm, "separation", (4.2, 4.8), rng)
    if H - C < 1.0:
        raise ConfigError(f"twin_corridors: separation {H:.1f} m leaves no wall between corridors")
    L, E = n * P, C
    # one period's features: a door recess in the corridor's south wall, a pilaster in its
    # north wall (the same in both corridors: the north one is a translated copy)
    dw = min(1.0, 0.4 * P)
    a = float(rng.uniform(0.1, P - dw - 0.1))
    c = float(rng.uniform(0.3, P - 0.3))
    depth = float(rng.uniform(0.2, 0.35))
    for yc in (0.0, H):
        lo, hi = yc - C / 2, yc + C / 2
        # the south wall: outer wall (south corridor) or the block's north face (north corridor)
        x0, x1 = (-E, L + E) if yc == 0.0 else (0.0, L)
        periodic_wall(b, x0, x1, lo, P, n, a, dw, depth)
        # the north wall: the block's south face (south corridor) or the outer wall (north)
        x0, x1 = (0.0, L) if yc == 0.0 else (-E, L + E)
        b.polyline([(x0, hi), (x1, hi)])
        for k in range(n):
            b.box(k * P + c, hi - 0.075, 0.4, 0.15)
    b.polyline([(-E, -C / 2), (-E, H + C / 2)])
    b.polyline([(L + E, -C / 2), (L + E, H + C / 2)])
    b.polyline([(0.0, C / 2), (0.0, H - C / 2)])
    b.polyline([(L, C / 2), (L, H - C / 2)])
    xs = P / 2
    west, east = -E / 2, L + E / 2
    ccw = [(east, 0.0), (east, H), (west, H), (west, 0.0), (xs, 0.0)]
    cw = [(west, 0.0), (west, H), (east, H), (east, 0.0), (xs, 0.0)]
    b.route = ccw + cw
    b.info.update(period=P, periods=n, length=L, corridor_width=C, separation=H,
                  twin_dx=0.0, twin_dy=H)  # fmt: skip
    return (xs, 0.0, 0.0)


GENERATORS = {
    "lobby": _gen_lobby,
    "corridor": _gen_corridor,
    "glass": _gen_glass,
    "hall": _gen_hall,
    "office": _gen_office,
    "atrium": _gen_atrium,
    "long_corridor": _gen_long_corridor,
    "building": _gen_building,
    "twin_rooms": _gen_twin_rooms,
    "twin_corridors": _gen_twin_corridors,
}


def build_world(
    config: WorldConfig,
    rng: np.random.Generator,
    name: str = "world",
    clearance: float = 0.55,
    *,
    other_bytes: float = 0.0,
) -> World:
    """Build a world (generator layout + explicit geometry) with its navigation grid.

    Args:
        config: World description.
        rng: Randomness for the layout (one variant per seed).
        name: Name used in error messages.
        clearance: Clearance the robot start must have; a random free start is chosen when
            the suggested one is too tight.
        other_bytes: Memory the rest of the run needs; with the navigation grid it must stay
            under `scanguard.sim.limits.MEMORY_LIMIT_BYTES`.

    Returns:
        The world.

    Raises:
        ConfigError: Empty or open world, no room for the robot, parameters the generator
            cannot lay out, or a world too large (geometry or navigation grid).
    """
    b = Builder()
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    if config.generator is not None:
        params = dict(config.params)
        try:
            start = GENERATORS[config.generator](b, rng, params)
        except (ValueError, IndexError, ZeroDivisionError, OverflowError) as exc:
            shown = {k: list(v) if isinstance(v, tuple) else v for k, v in params.items()}
            raise ConfigError(
                f"world {name!r}: generator {config.generator!r} cannot lay out a world with "
                f"params {shown} ({exc}); use larger sizes"
            ) from None
    for wall in config.walls:
        b.polyline([(p[0], p[1]) for p in wall.points], MATERIALS[wall.material], wall.closed)
    for c in config.circles:
        b.circle(c.center[0], c.center[1], c.radius, MATERIALS[c.material])
    if config.start is not None:
        start = config.start
    if not b.segs:
        raise ConfigError(f"world {name!r}: needs at least one wall segment")
    if len(b.segs) + len(b.circles) > MAX_PRIMITIVES:
        raise ConfigError(
            f"world {name!r}: {len(b.segs)} wall segments and {len(b.circles)} circles, more "
            f"than the limit of {MAX_PRIMITIVES:,}: lower the counts or raise the spacing in "
            "world.params, or give fewer walls"
        )
    segs = np.asarray(b.segs, dtype=np.float64).reshape(-1, 4)
    circles = np.asarray(b.circles, dtype=np.float64).reshape(-1, 3)
    st = np.asarray(start, dtype=np.float64)
    world = World(
        name=name,
        segments=segs,
        segment_material=np.asarray(b.mats, dtype=np.int8),
        circles=circles,
        circle_material=np.asarray(b.cmats, dtype=np.int8),
        start=st,
        info=dict(b.info),
        route=np.asarray(b.route, dtype=np.float64).reshape(-1, 2),
    )
    world.nav = nav_grid(segs, circles, st, config.grid_resolution, name, other_bytes)
    if not world.is_free(st[None, :2], clearance)[0]:
        if config.start is not None:
            raise ConfigError(f"world {name!r}: start {list(start)} is closer than {clearance} m "
                              "to a wall")  # fmt: skip
        xy = world.sample_free(rng, 1, clearance)[0]
        world.start = np.array([xy[0], xy[1], st[2]])
    log.debug("world %s: %d segments, %d circles, %.0f m² free", name, len(segs), len(circles),
              world.free_area())  # fmt: skip
    return world
