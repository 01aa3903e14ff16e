"""Loop-closure search of the ``graph`` back end: the candidates a judge then decides on.

Older nodes within the search's reach of the current estimate (`search_reach`:
``loop_search_maximum_distance``, or a multiple of the trajectory's uncertainty) and at least
``loop_min_travel`` back along the path are grouped into chains of consecutive nodes
(`candidate_chains`); each chain's centre gets a submap (its neighbours' scans in its own
frame, cached in `SubmapCache`), searched by a wide coarse correlative match and refined by a
fine one (`loop_candidates`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import relative, transform_points
from scanguard.matching.config import CorrelativeConfig
from scanguard.matching.correlative import (
    CorrelativeResult,
    correlative_match,
    match_to_map,
    second_peak,
)
from scanguard.matching.likelihood import LikelihoodGrid
from scanguard.slam.graph.closure import ClosureCandidate
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.local_map import GraphNode
from scanguard.slam.graph.solver import PoseGraphSolver

#: Chain centres whose submap is remembered (least recently used forgotten): a remembered
#: centre's submap is the one first built for it, from the estimates of that moment.
_MAX_SUBMAPS = 64
#: Bytes of likelihood grids held at once. A submap is 15 MB on average and up to 70 MB
#: (ACES: a 40 m corridor at 3 and 5 cm, pyramids of 3 and 6 levels), and only a few percent
#: of searches use one again (mostly the last one): 64 of them held by each of the three
#: instances of a run reached 1 GB. A remembered submap whose grids were dropped is rebuilt
#: from its recipe, bit for bit the same.
MAX_SUBMAP_BYTES = 48 * 2**20


@dataclass(frozen=True)
class SubmapRecipe:
    """What a submap is built from: its nodes and their poses in the centre's frame."""

    members: tuple[int, ...]  # accepted nodes of the chain, in order
    poses: NDArray[np.float64]  # ``(len(members), 3)``: each relative to the centre


def grid_bytes(maps: tuple[LikelihoodGrid, LikelihoodGrid]) -> int:
    """Bytes of a submap's pyramids and points."""
    return sum(g.stack.nbytes + g.points.nbytes for g in maps)


class SubmapCache:
    """Coarse and fine likelihood grids of chain centres, least recently used dropped.

    A centre's submap is fixed when it is first asked for (until `clear`): later searches
    use the same grids even though iSAM2 has moved the nodes a little since. What fixes it,
    the recipe, is small and kept for ``_MAX_SUBMAPS`` centres; the grids are large and kept
    only within ``max_bytes`` (rebuilt from the recipe, identically, when asked again).

    Args:
        max_bytes: Bytes of grids held at once (a larger submap is used once, not kept).
    """

    def __init__(self, max_bytes: int = MAX_SUBMAP_BYTES) -> None:
        self.max_bytes = max_bytes
        self._recipes: OrderedDict[int, SubmapRecipe] = OrderedDict()
        self._maps: OrderedDict[int, tuple[LikelihoodGrid, LikelihoodGrid]] = OrderedDict()
        self._bytes = 0
        self.builds = 0

    @property
    def held_bytes(self) -> int:
        """Bytes of the grids held now."""
        return self._bytes

    def clear(self) -> None:
        """Forget every submap (a closure moved the nodes they were built from)."""
        self._recipes.clear()
        self._maps.clear()
        self._bytes = 0

    def recipe(
        self, centre: int, nodes: list[GraphNode], est: NDArray[np.float64], cfg: GraphConfig
    ) -> SubmapRecipe:
        """The recipe of the chain around node ``centre`` (remembered, or made now)."""
        cached = self._recipes.get(centre)
        if cached is not None:
            self._recipes.move_to_end(centre)
            return cached
        lo = max(0, centre - cfg.loop_submap_nodes)
        hi = min(len(nodes), centre + cfg.loop_submap_nodes + 1)
        members = tuple(m for m in range(lo, hi) if nodes[m].accepted)
        poses = np.array([relative(est[centre], est[m]) for m in members], dtype=np.float64)
        out = SubmapRecipe(members, poses.reshape(-1, 3))
        self._recipes[centre] = out
        if len(self._recipes) > _MAX_SUBMAPS:
            gone, _ = self._recipes.popitem(last=False)
            self._drop(gone)
        return out

    def get(
        self, centre: int, nodes: list[GraphNode], est: NDArray[np.float64], cfg: GraphConfig
    ) -> tuple[LikelihoodGrid, LikelihoodGrid]:
        """The (coarse, fine) submap of the chain around node ``centre``, in its frame."""
        recipe = self.recipe(centre, nodes, est, cfg)
        cached = self._maps.get(centre)
        if cached is not None:
            self._maps.move_to_end(centre)
            return cached
        parts = [
            transform_points(pose, nodes[m].outline)
            for m, pose in zip(recipe.members, recipe.poses, strict=True)
        ]
        pts = np.concatenate(parts)
        maps = (
            LikelihoodGrid.from_points(pts, cfg.loop_matcher),
            LikelihoodGrid.from_points(pts, cfg.loop_fine),
        )
        self.builds += 1
        self._maps[centre] = maps
        self._bytes += grid_bytes(maps)
        while self._bytes > self.max_bytes and self._maps:
            self._drop(next(iter(self._maps)))
        return maps

    def _drop(self, centre: int) -> None:
        maps = self._maps.pop(centre, None)
        if maps is not None:
            self._bytes -= grid_bytes(maps)


class NodeIndex:
    """The nodes' path lengths and accepted flags as arrays, extended as nodes are added.

    The loop search filters every older node at each search (every few nodes): reading the
    two fields from each `GraphNode` made that O(nodes) in Python per search, the largest
    part of a late search on a long log. Both fields are final once a node is in the list
    (the back end sets them before appending it), so rows, once read, stay valid.
    """

    def __init__(self) -> None:
        self._path = np.zeros(0)
        self._accepted = np.zeros(0, dtype=bool)
        self._n = 0

    def arrays(
        self, nodes: list[GraphNode], n: int
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """``(path, accepted)`` of nodes ``0..n-1``."""
        if n > self._path.shape[0]:
            size = max(n, 2 * self._path.shape[0], 64)  # doubling: O(1) amortised per node
            path = np.zeros(size)
            accepted = np.zeros(size, dtype=bool)
            path[: self._n] = self._path[: self._n]
            accepted[: self._n] = self._accepted[: self._n]
            self._path, self._accepted = path, accepted
        for i in range(self._n, n):
            self._path[i] = nodes[i].path
            self._accepted[i] = nodes[i].accepted
        self._n = max(self._n, n)
        return self._path[:n], self._accepted[:n]


@dataclass(frozen=True)
class SearchReach:
    """How far a loop search looks: candidate radius (m) and the coarse window."""

    radius: float
    window_xy: float
    window_theta: float


def search_reach(
    solver: PoseGraphSolver, k: int, cfg: GraphConfig, *, wide: bool = True
) -> SearchReach:
    """The reach of node ``k``'s loop search (see ``GraphConfig.loop_search_sigmas``).

    ``wide`` False (a search between two wide ones, ``loop_wide_every``): the fixed reach.

    The newest node's marginal comes from iSAM2's Bayes tree root (~0.3 ms for 3000 nodes).
    It is taken against the first node, so for a place seen recently it overstates the
    relative uncertainty: the search then only looks wider than it needs (the judges decide).
    """
    if cfg.loop_search_sigmas <= 0 or not wide:
        return reach_from_marginal(None, cfg)
    try:
        cov = np.asarray(solver.isam.marginalCovariance(k), dtype=np.float64)
    except RuntimeError:  # gtsam could not form the marginal: the fixed reach
        return reach_from_marginal(None, cfg)
    return reach_from_marginal(cov, cfg)


def reach_from_marginal(cov: NDArray[np.float64] | None, cfg: GraphConfig) -> SearchReach:
    """The reach of a wide search from the node's marginal covariance ``(3, 3)``.

    ``loop_search_sigmas`` standard deviations of the position (largest eigenvalue) and of
    the heading, never below the fixed reach and window, at most ``loop_search_max_radius``
    and half a turn. None, a non-finite covariance or ``loop_search_sigmas`` 0: the fixed
    reach. The consistency gate (`scanguard.slam.graph.consistency`) bounds a closure's claim
    by the same reach, so both read it here.
    """
    base = SearchReach(
        cfg.loop_search_maximum_distance, cfg.loop_matcher.window_xy, cfg.loop_matcher.window_theta
    )
    if cfg.loop_search_sigmas <= 0 or cov is None or not np.all(np.isfinite(cov)):
        return base
    sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
    sigma_th = math.sqrt(max(float(cov[2, 2]), 0.0))
    reach = min(cfg.loop_search_sigmas * sigma_xy, cfg.loop_search_max_radius)
    turn = min(cfg.loop_search_sigmas * sigma_th, math.pi)
    return SearchReach(
        max(base.radius, reach), max(base.window_xy, reach), max(base.window_theta, turn)
    )


def relative_covariance(
    isam: Any, t: int, k: int, rel: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """Covariance ``(3, 3)`` of node ``k``'s pose seen from node ``t`` (``rel``: that pose).

    First order, from iSAM2's joint marginal of the two nodes (0.05-2.3 ms on Intel's 5121
    nodes, session 19): ``rel = t^-1 k`` moves with ``k``'s perturbation as the identity and
    with ``t``'s as ``-Ad(rel^-1)`` (gtsam's right perturbations, checked numerically in the
    tests). Where a place was seen a few metres of path ago the two marginals against the
    first node are large and nearly equal, and this is small. None when gtsam cannot form it.
    """
    try:
        joint = isam.jointMarginalCovariance([t, k])
        c_tt = np.asarray(joint.at(t, t), dtype=np.float64)
        c_tk = np.asarray(joint.at(t, k), dtype=np.float64)
        c_kk = np.asarray(joint.at(k, k), dtype=np.float64)
    except RuntimeError:
        return None
    x, y, th = (float(v) for v in rel)
    c, s = math.cos(th), math.sin(th)
    # rel^-1 = (-(c x + s y), s x - c y, -th); Pose2's adjoint of (a, b, phi) is
    # [[cos phi, -sin phi, b], [sin phi, cos phi, -a], [0, 0, 1]]
    ia, ib = -(c * x + s * y), s * x - c * y
    h = -np.array([[c, s, ib], [-s, c, -ia], [0.0, 0.0, 1.0]])
    out: NDArray[np.float64] = h @ c_tt @ h.T + h @ c_tk + c_tk.T @ h.T + c_kk
    return 0.5 * (out + out.T)


class FailureMemory:
    """Centres whose coarse loop search found nothing, for ``loop_fail_memory`` rounds.

    The nearest node of a chain, by a graph that has drifted, may be the wrong end of it: its
    submap does not hold what the scan sees, and every due search would try it again while the
    right part of the same chain, a few metres on, is never searched (ACES, session 23: 11
    searches in a row at one submap, then a wrong closure one door along).
    """

    def __init__(self, rounds: int) -> None:
        self.rounds = int(rounds)
        self._failed: dict[int, int] = {}

    def add(self, centre: int, round_: int) -> None:
        """Centre ``centre`` failed in search round ``round_``."""
        if self.rounds > 0:
            self._failed[centre] = round_

    def recent(self, round_: int) -> list[int]:
        """The centres that failed within the last ``rounds`` rounds before ``round_``."""
        self._failed = {c: r for c, r in self._failed.items() if round_ - r <= self.rounds}
        return [c for c, r in self._failed.items() if r < round_]


def candidate_chains(
    nodes: list[GraphNode],
    est: NDArray[np.float64],
    k: int,
    cfg: GraphConfig,
    index: NodeIndex | None = None,
    radius: float | None = None,
    avoid: Iterable[int] = (),
) -> list[int]:
    """Centres of candidate chains for node ``k``, nearest first.

    ``index`` (kept by the caller across searches) saves re-reading every node's fields;
    ``radius`` (default ``loop_search_maximum_distance``) is the search's reach. A centre is
    never a node within ``loop_submap_nodes`` of one in ``avoid`` (centres whose submaps
    just failed to match: `GraphConfig.loop_fail_memory`); a chain is then centred on its
    nearest other node.
    """
    n = k
    if n <= 0:
        return []
    if index is None:
        path = np.array([nodes[i].path for i in range(n)])
        acc = np.array([nodes[i].accepted for i in range(n)])
    else:
        path, acc = index.arrays(nodes, n)
    dist = np.hypot(*(est[:n, :2] - est[k, :2]).T)
    mask = acc & (nodes[k].path - path >= cfg.loop_min_travel)
    mask &= dist <= (cfg.loop_search_maximum_distance if radius is None else radius)
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    usable = np.ones(n, dtype=bool)
    for a in avoid:
        usable[max(0, a - cfg.loop_submap_nodes) : a + cfg.loop_submap_nodes + 1] = False
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    centres = []
    for chain in np.split(idx, breaks):
        if len(chain) < cfg.loop_match_minimum_chain_size:
            continue
        free = chain[usable[chain]]
        if len(free):
            centres.append(int(free[np.argmin(dist[free])]))
    centres.sort(key=lambda c: float(dist[c]))
    return centres[:2]


def _windowed(matcher: CorrelativeConfig, reach: SearchReach) -> CorrelativeConfig:
    """``matcher`` with the coarse window of ``reach`` (itself when they already agree)."""
    if (reach.window_xy, reach.window_theta) == (matcher.window_xy, matcher.window_theta):
        return matcher
    return matcher.model_copy(
        update={"window_xy": reach.window_xy, "window_theta": reach.window_theta}
    )


def loop_candidates(
    k: int,
    nodes: list[GraphNode],
    solver: PoseGraphSolver,
    submaps: SubmapCache,
    cfg: GraphConfig,
    stats: dict[str, float],
    index: NodeIndex | None = None,
    failures: FailureMemory | None = None,
) -> Iterator[ClosureCandidate]:
    """The loop-closure candidates of node ``k``, one per chain that matches, nearest first.

    Lazily: the caller judges each candidate before the next chain is searched, and each
    search reads the solver's estimates as they are then (a refused closure may have
    rebuilt them). ``failures`` (kept by the caller) remembers the centres whose coarse
    search found nothing, and steers the next searches to other nodes of their chains.
    """
    node = nodes[k]
    stats["loop_rounds"] = stats.get("loop_rounds", 0.0) + 1
    wide = stats["loop_rounds"] % cfg.loop_wide_every == 0
    reach = search_reach(solver, k, cfg, wide=wide)
    stats["loop_reach_max_m"] = max(stats.get("loop_reach_max_m", 0.0), reach.radius)
    coarse_cfg = _windowed(cfg.loop_matcher, reach)
    relative_window = wide and cfg.loop_window == "relative" and cfg.loop_search_sigmas > 0
    avoid = () if failures is None else failures.recent(int(stats["loop_rounds"]))
    for centre in candidate_chains(nodes, solver.est, k, cfg, index, reach.radius, avoid):
        stats["loop_searches"] += 1
        coarse_map, fine_map = submaps.get(centre, nodes, solver.est, cfg)
        initial = relative(solver.est[centre], solver.est[k])
        search_cfg = coarse_cfg
        prior_cov: NDArray[np.float64] | None = None
        if relative_window:
            prior_cov = relative_covariance(solver.isam, centre, k, initial)
            search_cfg = _windowed(cfg.loop_matcher, reach_from_marginal(prior_cov, cfg))
        coarse = correlative_match(node.points, coarse_map, initial, search_cfg)
        if not coarse.found or coarse.score < cfg.loop_min_response:
            if failures is not None:
                failures.add(centre, int(stats["loop_rounds"]))
            continue
        if not relative_window:  # formed only for a candidate (its `disagreement_sigmas`)
            prior_cov = relative_covariance(solver.isam, centre, k, initial)
        m, fine = match_to_map(node.points, fine_map, coarse.pose, cfg.loop_fine)
        pose = np.asarray(m.pose if m.ok else fine.pose, dtype=np.float64)
        if not np.all(np.isfinite(pose)):
            continue
        alias_pose, alias_ratio = _alias(node.points, coarse_map, initial, coarse, search_cfg, cfg)
        yield ClosureCandidate(
            node=k,
            target_node=centre,
            scan_index=node.scan_index,
            target_scan_index=nodes[centre].scan_index,
            pose=pose,
            score=float(fine.score),
            coarse_score=float(coarse.score),
            covariance=np.asarray(fine.covariance, dtype=np.float64),
            source=node.scan,
            target=nodes[centre].scan,
            match=m,
            prior_pose=initial,
            path_gap=node.path - nodes[centre].path,
            prior_covariance=prior_cov,
            alias_pose=alias_pose,
            alias_ratio=alias_ratio,
        )


def _alias(
    points: NDArray[np.float64],
    grid: LikelihoodGrid,
    initial: NDArray[np.float64],
    coarse: CorrelativeResult,
    search_cfg: CorrelativeConfig,
    cfg: GraphConfig,
) -> tuple[NDArray[np.float64] | None, float]:
    """The coarse search's second peak and its response ratio (`ClosureCandidate.alias_pose`)."""
    if cfg.loop_alias_radius <= 0.0:
        return None, float("nan")
    alt = second_peak(
        points,
        grid,
        initial,
        coarse,
        search_cfg,
        radius=cfg.loop_alias_radius,
        min_ratio=cfg.loop_alias_min_ratio,
    )
    if not alt.found:
        return None, 0.0
    return np.asarray(alt.pose, dtype=np.float64), float(alt.score / max(coarse.score, 1e-12))


__all__ = [
    "MAX_SUBMAP_BYTES",
    "FailureMemory",
    "NodeIndex",
    "SearchReach",
    "SubmapCache",
    "SubmapRecipe",
    "candidate_chains",
    "grid_bytes",
    "loop_candidates",
    "reach_from_marginal",
    "relative_covariance",
    "search_reach",
]
