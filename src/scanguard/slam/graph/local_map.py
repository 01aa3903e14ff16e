"""Scan-to-local-map matching of the ``graph`` back end: the sequential factor of a node.

A node's scan is matched by the correlative matcher against a likelihood grid of the last
``local_map_nodes`` accepted scans at their current estimates (`local_map_points`), seeded by
odometry, refined by point-to-line ICP (`refine`); along a direction the scan cannot see,
odometry decides (`degenerate_slide`). `GraphNode` is what the back end keeps of a node.

Before the match, the local map loses the points its newer scans saw through
(`carve_seen_through`), and the node's scan the points its older scans saw through
(`moving_source_points`): people walking along with the robot (`scanguard.slam.free_space`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.geometry import compose, relative, transform_points, wrap_angle
from scanguard.matching.correlative import correlative_match, default_refine_config
from scanguard.matching.icp import match_starts
from scanguard.matching.likelihood import LikelihoodGrid, outline_points, thin_points
from scanguard.scan import LaserScan
from scanguard.slam.free_space import RangeView
from scanguard.slam.graph.config import GraphConfig


@dataclass(frozen=True)
class NodeShape:
    """How a node's points, outline and view follow from its scan (one per back end).

    Args:
        max_range: Beams at or beyond this range (m) are not points (None: all valid beams).
        spacing: Spacing of the outline's filled-in points (m).
        carve: Whether nodes have views (``carve_frames`` > 0).
    """

    max_range: float | None
    spacing: float
    carve: bool

    def geometry(self, scan: LaserScan) -> NodeGeometry:
        """The scan's points, outline and view: equal bit for bit every time it is asked."""
        pts = np.asarray(scan.points(np.float64), dtype=np.float64).reshape(-1, 2)
        if self.max_range is not None and len(pts):
            pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < self.max_range]
        outline = outline_points(pts, float(scan.angle_increment), spacing=self.spacing)
        view = RangeView.of(scan) if self.carve else None
        return NodeGeometry(pts, outline, view)


@dataclass(frozen=True)
class NodeGeometry:
    """What a node's scan gives the matches (see `GraphNode`)."""

    points: NDArray[np.float64]  # sensor-frame points: the source of every match
    outline: NDArray[np.float64]  # the same with the surfaces between hits filled in: maps
    view: RangeView | None  # the beams, to carve older points it saw through


@dataclass(eq=False, slots=True)  # no per-node __dict__: one node per 0.1 m
class GraphNode:
    """A node of the pose graph.

    Its points, outline and view are derived from its scan by ``shape``. They are held while
    the node may be in the local map (`hold`); after that only a loop search reads them, now
    and then, and they are derived again (bit for bit the same) rather than kept: a node's
    float64 outline is about 9 KB, held by each instance of a run for each 0.1 m travelled.
    The scan itself is the recording's own object, not a copy.
    """

    scan_index: int
    odom: NDArray[np.float64]  # robot odometry pose at the node's scan
    scan: LaserScan
    shape: NodeShape
    accepted: bool  # the scan went into the maps
    path: float  # odometry path length from the first node (m)
    sensor_odom: NDArray[np.float64] | None = None  # sensor pose in the odometry frame
    _held: NodeGeometry | None = field(default=None, repr=False)
    # the outline placed at the estimate it was last asked at (bytes of that pose, points)
    _placed: tuple[bytes, NDArray[np.float64]] | None = field(default=None, repr=False)

    @property
    def held(self) -> bool:
        """Whether the derived arrays are kept (`hold`) rather than derived when read."""
        return self._held is not None

    def hold(self) -> None:
        """Keep the derived arrays until `release`."""
        if self._held is None:
            self._held = self.shape.geometry(self.scan)

    def release(self) -> None:
        """Stop keeping the derived arrays (they are derived again when read)."""
        self._held = None
        self._placed = None

    def placed_outline(self, pose: NDArray[np.float64]) -> NDArray[np.float64]:
        """The outline in the map frame at ``pose`` (read-only).

        While the node is held, the array of the last call is given again when ``pose`` is the
        same bit for bit: iSAM2 leaves ~85 % of a local map's estimates untouched from one
        node to the next (Intel), and placing 24 outlines was 5 % of a run.
        """
        key = np.ascontiguousarray(pose, dtype=np.float64).tobytes()
        if self._placed is not None and self._placed[0] == key:
            return self._placed[1]
        out = np.asarray(transform_points(pose, self.outline), np.float64)
        out.flags.writeable = False
        if self._held is not None:
            self._placed = (key, out)
        return out

    def geometry(self) -> NodeGeometry:
        """Points, outline and view: the held ones, or derived now and not kept."""
        if self._held is not None:
            return self._held
        out = self.shape.geometry(self.scan)
        # derived for a rare read of an old node: leave no cached points on its scan either
        self.scan.release()
        return out

    @property
    def points(self) -> NDArray[np.float64]:
        """Sensor-frame points within the range limit: the source of every match."""
        return self.geometry().points

    @property
    def outline(self) -> NDArray[np.float64]:
        """The points with the surfaces between hits filled in: what maps are built from."""
        return self.geometry().outline

    @property
    def view(self) -> RangeView | None:
        """The beams, to carve older points it saw through (None: carving off)."""
        return self.geometry().view


def local_map_points(
    nodes: list[GraphNode],
    est: NDArray[np.float64],
    predicted: NDArray[np.float64],
    cfg: GraphConfig,
    source: NDArray[np.float64],
    current: RangeView | None = None,
    current_odom: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64]]:
    """The local map: recent accepted nodes' points near ``predicted``, and the source to match.

    Returns the map points (None: no such node) and the points of ``source`` (the scan about
    to be matched, sensor frame) to match them with. With ``carve_frames`` > 0, ``current``
    (the view of that scan, at ``predicted``) and the newest nodes carve what they saw through
    out of the map, and the source loses what the older nodes saw through (kept whole when
    fewer than half its points would remain). Views and points are placed relative to each
    other by the odometry given (``current_odom``: the sensor's pose in the odometry frame),
    not by the graph's estimates: those are what the moving points bias, and estimates
    pulled along by people would see them standing still.
    """
    keep: list[int] = []
    for i in range(len(nodes) - 1, -1, -1):
        if len(keep) == cfg.local_map_nodes:
            break
        if nodes[i].accepted:
            keep.append(i)
    near = [
        i for i in keep if math.hypot(*(est[i, :2] - predicted[:2])) <= cfg.local_map_max_distance
    ]
    if not near:
        return None, source
    parts = [nodes[i].placed_outline(est[i]) for i in near]
    if cfg.carve_frames > 0 and current_odom is not None:
        parts = carve_seen_through(parts, near, nodes, est, current, current_odom, cfg)
        moving = moving_source_points(source, predicted, current_odom, nodes, near, cfg)
        if 2 * int(moving.sum()) < len(source):
            source = source[~moving]
    local = thin_points(np.concatenate(parts), cfg.local_map_thin)
    return (local if len(local) >= 3 else None), source


def moving_source_points(
    pts: NDArray[np.float64],
    predicted: NDArray[np.float64],
    current_odom: NDArray[np.float64],
    nodes: list[GraphNode],
    near: list[int],
    cfg: GraphConfig,
) -> NDArray[np.bool_]:
    """Per point of the scan about to be matched: an older node's beams passed beyond it.

    Something stands now where the local map's own scans saw free space: a person walking
    along with the robot, whom every recent scan shows at the same relative place. Up to
    ``carve_frames`` nodes spread over the local map test it (the oldest see the most).
    """
    world = transform_points(predicted, pts)
    gone = np.zeros(len(pts), dtype=bool)
    for i in near[:: max(1, len(near) // max(cfg.carve_frames, 1))]:
        view, odom = nodes[i].view, nodes[i].sensor_odom
        if view is not None and odom is not None:
            pose = compose(predicted, relative(current_odom, odom))
            gone |= view.seen_through(pose, world, cfg.carve_margin, cfg.carve_lateral)
    return gone


def carve_seen_through(
    parts: list[NDArray[np.float64]],
    near: list[int],
    nodes: list[GraphNode],
    est: NDArray[np.float64],
    current: RangeView | None,
    current_odom: NDArray[np.float64],
    cfg: GraphConfig,
) -> list[NDArray[np.float64]]:
    """``parts`` (world points of nodes ``near``, newest first) less what newer views saw through.

    The current scan and the ``carve_frames - 1`` newest nodes carve every older node's points.
    """
    views: list[tuple[int, NDArray[np.float64], RangeView]] = []
    if current is not None:
        views.append((len(nodes), current_odom, current))
    for i in near[: max(cfg.carve_frames - 1, 0)]:
        view, odom = nodes[i].view, nodes[i].sensor_odom
        if view is not None and odom is not None:
            views.append((i, odom, view))
    out = []
    for i, pts in zip(near, parts, strict=True):
        gone = np.zeros(len(pts), dtype=bool)
        base = nodes[i].sensor_odom
        for j, odom, view in views:
            if j > i and base is not None:
                pose = compose(est[i], relative(base, odom))
                gone |= view.seen_through(pose, pts, cfg.carve_margin, cfg.carve_lateral)
        out.append(pts[~gone])
    return out


def match_local(
    pts: NDArray[np.float64],
    local: NDArray[np.float64],
    predicted: NDArray[np.float64],
    cfg: GraphConfig,
    stats: dict[str, float],
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Pose and covariance of ``pts`` matched to ``local`` (None: no good enough match)."""
    grid = LikelihoodGrid.from_points(local, cfg.sequential)
    corr = correlative_match(pts, grid, predicted, cfg.sequential)
    pose = np.asarray(corr.pose, dtype=np.float64)
    if not corr.found or corr.score < cfg.min_response or not np.all(np.isfinite(pose)):
        return None
    if cfg.refine:
        pose = refine(grid, pts, pose, predicted, float(corr.theta_step), cfg)
    return degenerate_slide(grid, pts, pose, predicted, corr.covariance, cfg, stats)


def refine(
    grid: LikelihoodGrid,
    pts: NDArray[np.float64],
    pose: NDArray[np.float64],
    predicted: NDArray[np.float64],
    theta_step: float,
    cfg: GraphConfig,
) -> NDArray[np.float64]:
    """Point-to-line ICP against the map from the correlative pose and from the prediction.

    Along a weakly constrained direction ICP stops wherever its start leaves it, and the
    correlative pose is only good to a cell: started there alone it drifts short by ~1 %
    of the travel in the simulator's rooms. Started from both, the run with the smaller
    mean residual is kept, provided it stays within two cells / two angular steps of the
    correlative pose (a wrong prediction converges elsewhere and loses).
    """
    icfg = default_refine_config(cfg.sequential)
    limit_t = 2.0 * grid.resolution
    limit_r = 2.0 * theta_step
    best: tuple[float, NDArray[np.float64]] | None = None
    # a correlative search that kept the prediction (most nodes of a slow robot) would run
    # the same ICP twice and keep the first: one run gives the same pose
    same = cfg.odometry_is_prior or np.array_equal(pose, predicted)
    starts: list[ArrayLike | None] = [pose] if same else [pose, predicted]
    # both starts in one call: the local map's search structures are built once
    for m in match_starts("point_to_line", pts, grid.points, starts, icfg):
        if not m.ok:
            continue
        d = relative(pose, np.asarray(m.pose, dtype=np.float64))
        if math.hypot(d[0], d[1]) > limit_t or abs(float(wrap_angle(d[2]))) > limit_r:
            continue
        if best is None or m.mean_residual < best[0]:
            best = (float(m.mean_residual), np.asarray(m.pose, dtype=np.float64))
    return pose if best is None else best[1]


def degenerate_slide(
    grid: LikelihoodGrid,
    pts: NDArray[np.float64],
    pose: NDArray[np.float64],
    predicted: NDArray[np.float64],
    covariance: NDArray[np.float64],
    cfg: GraphConfig,
    stats: dict[str, float],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Let odometry decide a direction the scan cannot see (see ``degenerate_tolerance``).

    The response-surface covariance only spans the neighbourhood the matcher scored, so
    in a featureless corridor it understates the freedom along the corridor, and the best
    pose there is whichever cell noise favours: the graph would then trust a slide.
    """
    cov = np.asarray(covariance, dtype=np.float64).copy()
    if cfg.odometry_is_prior:
        return pose, cov
    _, vecs = np.linalg.eigh(cov[:2, :2])
    d = vecs[:, 1]
    best = grid.score(pts, pose)
    step = np.array([d[0], d[1], 0.0]) * cfg.degenerate_probe
    worst_probe = min(grid.score(pts, pose + step), grid.score(pts, pose - step))
    if worst_probe < (1.0 - cfg.degenerate_tolerance) * best:
        return pose, cov
    stats["matches_degenerate"] += 1
    slid = pose.copy()
    slid[:2] += float(np.dot(predicted[:2] - pose[:2], d)) * d
    d3 = np.array([d[0], d[1], 0.0])
    return slid, cov + cfg.degenerate_sigma**2 * np.outer(d3, d3)


__all__ = [
    "GraphNode",
    "NodeGeometry",
    "NodeShape",
    "carve_seen_through",
    "degenerate_slide",
    "local_map_points",
    "match_local",
    "moving_source_points",
    "refine",
]
