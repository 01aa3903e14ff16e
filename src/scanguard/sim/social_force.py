"""The social-force kernel that moves the simulator's pedestrians (`scanguard.sim.people`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@njit(cache=True)
def social_forces(
    pos: FloatArray,
    vel: FloatArray,
    desired: FloatArray,
    radius: FloatArray,
    group: NDArray[np.int64],
    segs: FloatArray,
    circles: FloatArray,
    robot_x: float,
    robot_y: float,
    robot_r: float,
    prm: FloatArray,
) -> FloatArray:  # pragma: no cover - compiled
    """Social forces (Helbing-Molnar style) on every agent, O(N² + N·K) compiled loops.

    ``prm`` = (relaxation_time, person_strength, person_range, wall_strength, wall_range,
    robot_strength, robot_range).
    """
    tau, a_p, b_p, a_w, b_w, a_r, b_r = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6]
    n = pos.shape[0]
    f = np.empty((n, 2))
    for i in range(n):
        fx = (desired[i, 0] - vel[i, 0]) / tau
        fy = (desired[i, 1] - vel[i, 1]) / tau
        sp = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2)
        vx = vel[i, 0] / sp if sp > 1e-6 else 0.0
        vy = vel[i, 1] / sp if sp > 1e-6 else 0.0
        gx = 0.0
        gy = 0.0
        gn = 0
        for j in range(n):
            if j == i:
                continue
            dx = pos[i, 0] - pos[j, 0]
            dy = pos[i, 1] - pos[j, 1]
            d = max(math.sqrt(dx * dx + dy * dy), 1e-6)
            nx = dx / d
            ny = dy / d
            # others ahead matter more than those behind (anisotropy)
            aniso = 0.3 + 0.35 * (1.0 - (nx * vx + ny * vy))
            same = group[i] >= 0 and group[i] == group[j]
            a = 0.3 * a_p if same else a_p
            m = a * math.exp((radius[i] + radius[j] - d) / b_p) * aniso
            fx += m * nx
            fy += m * ny
            if same:
                gx += pos[j, 0]
                gy += pos[j, 1]
                gn += 1
        if gn > 0:
            # group cohesion: drift back towards the others when straggling
            ox = (gx + pos[i, 0]) / (gn + 1) - pos[i, 0]
            oy = (gy + pos[i, 1]) / (gn + 1) - pos[i, 1]
            d = math.sqrt(ox * ox + oy * oy)
            if d > 0.8:
                fx += (d - 0.8) * ox / d
                fy += (d - 0.8) * oy / d
        for k in range(segs.shape[0]):
            ex = segs[k, 2] - segs[k, 0]
            ey = segs[k, 3] - segs[k, 1]
            wx = pos[i, 0] - segs[k, 0]
            wy = pos[i, 1] - segs[k, 1]
            t = min(max((wx * ex + wy * ey) / max(ex * ex + ey * ey, 1e-12), 0.0), 1.0)
            dx = wx - t * ex
            dy = wy - t * ey
            d = max(math.sqrt(dx * dx + dy * dy), 1e-6)
            if d > 3.0:
                continue
            m = a_w * math.exp((radius[i] - d) / b_w)
            fx += m * dx / d
            fy += m * dy / d
        for k in range(circles.shape[0]):
            dx = pos[i, 0] - circles[k, 0]
            dy = pos[i, 1] - circles[k, 1]
            d = max(math.sqrt(dx * dx + dy * dy), 1e-6)
            gap = d - circles[k, 2]
            if gap > 3.0:
                continue
            m = a_w * math.exp((radius[i] - gap) / b_w)
            fx += m * dx / d
            fy += m * dy / d
        dx = pos[i, 0] - robot_x
        dy = pos[i, 1] - robot_y
        d = max(math.sqrt(dx * dx + dy * dy), 1e-6)
        m = a_r * math.exp((radius[i] + robot_r - d) / b_r)
        f[i, 0] = fx + m * dx / d
        f[i, 1] = fy + m * dy / d
    return f
