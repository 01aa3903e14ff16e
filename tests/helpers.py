"""Synthetic scans with known geometry for tests (deterministic, no simulator needed)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import compose
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

RPLIDAR = SensorInfo(
    name="RPLidar A3",
    n_beams=1440,
    angle_min=-np.pi,
    angle_increment=2 * np.pi / 1440,
    range_min=0.15,
    range_max=25.0,
    rate_hz=10.0,
)


def room_segments(
    width: float = 10.0, height: float = 6.0, pillars: bool = True
) -> NDArray[np.float64]:
    """Wall segments ``(K, 4)`` (x0, y0, x1, y1) of a room centred at the origin.

    The room is deliberately asymmetric (an alcove and square pillars) so that ICP has a
    unique answer.
    """
    w, h = width / 2, height / 2
    segs = [
        (-w, -h, w, -h),
        (w, -h, w, h * 0.3),
        (w, h * 0.3, w + 1.5, h * 0.3),
        (w + 1.5, h * 0.3, w + 1.5, h),
        (w + 1.5, h, -w, h),
        (-w, h, -w, -h),
    ]
    if pillars:
        for cx, cy, r in [(-2.0, 1.2, 0.25), (2.5, -1.0, 0.35), (-3.1, -1.9, 0.2)]:
            segs += [
                (cx - r, cy - r, cx + r, cy - r),
                (cx + r, cy - r, cx + r, cy + r),
                (cx + r, cy + r, cx - r, cy + r),
                (cx - r, cy + r, cx - r, cy - r),
            ]
    return np.array(segs, dtype=np.float64)


def corridor_segments(length: float = 60.0, width: float = 2.0) -> NDArray[np.float64]:
    """Two long parallel walls: featureless along x (degenerate for ICP)."""
    return np.array(
        [
            (-length / 2, -width / 2, length / 2, -width / 2),
            (-length / 2, width / 2, length / 2, width / 2),
        ],
        dtype=np.float64,
    )


def raycast(
    segments: NDArray[np.float64],
    pose: NDArray[np.float64] | tuple[float, float, float],
    sensor: SensorInfo = RPLIDAR,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> NDArray[np.float32]:
    """Exact ranges from ``pose`` to the nearest segment per beam (inf when nothing is hit)."""
    px, py, pth = (float(v) for v in pose)
    ang = pth + sensor.angle_min + sensor.angle_increment * np.arange(sensor.n_beams)
    dx, dy = np.cos(ang)[:, None], np.sin(ang)[:, None]
    x0, y0, x1, y1 = (segments[:, i][None, :] for i in range(4))
    ex, ey = x1 - x0, y1 - y0
    denom = dx * ey - dy * ex
    wx, wy = x0 - px, y0 - py
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * ey - wy * ex) / denom
        u = (wx * dy - wy * dx) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (u >= 0) & (u <= 1)
    t = np.where(hit, t, np.inf).min(axis=1)
    if noise > 0:
        rng = rng or np.random.default_rng(0)
        t = t + rng.normal(0.0, noise, size=t.shape)
    t = np.where(t > sensor.range_max, np.inf, t)
    return t.astype(np.float32)


def make_scan(
    segments: NDArray[np.float64],
    pose: NDArray[np.float64] | tuple[float, float, float],
    stamp: float = 0.0,
    sensor: SensorInfo = RPLIDAR,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> LaserScan:
    """A `LaserScan` seen from ``pose`` in the world described by ``segments``."""
    return LaserScan.from_sensor(sensor, stamp, raycast(segments, pose, sensor, noise, rng))


def make_sequence(
    segments: NDArray[np.float64],
    steps: NDArray[np.float64],
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
    sensor: SensorInfo = RPLIDAR,
    noise: float = 0.0,
    seed: int = 0,
    name: str = "synthetic",
) -> ScanSequence:
    """A sequence driven by relative ``steps`` ``(N-1, 3)``, with exact reference poses."""
    rng = np.random.default_rng(seed)
    poses = [np.asarray(start, dtype=np.float64)]
    for st in steps:
        poses.append(compose(poses[-1], st))
    ref = np.array(poses)
    rate = sensor.rate_hz or 10.0
    scans = [
        make_scan(segments, p, stamp=i / rate, sensor=sensor, noise=noise, rng=rng)
        for i, p in enumerate(ref)
    ]
    return ScanSequence(
        name=name, scans=scans, sensor=sensor, reference=ref, reference_kind="ground_truth"
    )


def small_room_walk(
    step_seed: int, noise_seed: int, n: int = 13, sensor: SensorInfo | None = None
) -> tuple[ScanSequence, list[NDArray[np.float64]]]:
    """A short straight-ish walk in the room (``n`` scans) and its true relative poses.

    The shared fixture of tests that inject known match errors into small pair stores.
    """
    from scanguard.geometry import relative

    rng = np.random.default_rng(step_seed)
    steps = np.column_stack(
        [rng.uniform(0.05, 0.15, n - 1), rng.uniform(-0.03, 0.03, n - 1), np.zeros(n - 1)]
    )
    seq = make_sequence(
        room_segments(), steps, start=(-1.0, -0.5, 0.1), sensor=sensor or RPLIDAR, seed=noise_seed
    )
    ref = seq.reference
    return seq, [relative(ref[i], ref[i + 1]) for i in range(n - 1)]


#: The robot's motion per scan in `pace_walk` (0.8 m/s at 10 Hz).
PACE_STEP = np.array([0.08, 0.0, 0.0])


def box_segments(cx: float, cy: float, r: float = 0.25) -> list[tuple[float, float, float, float]]:
    """The four sides of a square of half-width ``r`` centred at ``(cx, cy)``."""
    return [
        (cx - r, cy - r, cx + r, cy - r),
        (cx + r, cy - r, cx + r, cy + r),
        (cx + r, cy + r, cx - r, cy + r),
        (cx - r, cy + r, cx - r, cy - r),
    ]


def pace_walk(n: int) -> tuple[list[LaserScan], list[np.ndarray]]:
    """The robot drives along a corridor with pillars; four people keep pace beside it."""
    room = np.vstack(
        [corridor_segments(length=60.0, width=4.0)]
        + [np.array(box_segments(x, 1.9, 0.2)) for x in np.arange(-20.0, 20.0, 3.0)]
    )
    scans, poses = [], []
    pose = np.array([-3.0, -0.2, 0.0])
    for k in range(n):
        ahead = ((1.0, 1.2), (1.5, -1.1), (0.3, 1.4), (2.2, 0.9))
        people = [(pose[0] + dx, pose[1] + dy) for dx, dy in ahead]
        segs = np.vstack([room, *(np.array(box_segments(x, y)) for x, y in people)])
        scans.append(make_scan(segs, pose, stamp=0.1 * k))
        poses.append(pose.copy())
        pose = compose(pose, PACE_STEP)
    return scans, poses


class ScanLookup:
    """Which scan of ``scans`` a points array handed to a matcher came from.

    By identity first; the matcher may also get a subset of a scan's points (the free-space
    filter leaves out what moved), found by its first point.
    """

    def __init__(self, scans: list[LaserScan]) -> None:
        self.points = [s.points() for s in scans]
        self.ids = {id(p): i for i, p in enumerate(self.points)}

    def __call__(self, pts: NDArray[np.float32]) -> int:
        """The index of the scan ``pts`` belongs to."""
        found = self.ids.get(id(pts))
        if found is not None:
            return found
        for i, p in enumerate(self.points):
            if len(pts) and bool((p == pts[0]).all(axis=1).any()):
                return i
        raise KeyError("points of no known scan")
