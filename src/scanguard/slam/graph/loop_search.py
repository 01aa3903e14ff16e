"""Loop-closure search of the ``graph`` back end: the candidates a judge then decides on.

Older nodes within ``loop_search_maximum_distance`` of the current estimate (and at least
``loop_min_travel`` back along the path) are grouped into chains of consecutive nodes
(`candidate_chains`); each chain's centre gets a submap (its neighbours' scans in its own
frame, cached in `SubmapCache`), searched by a wide coarse correlative match and refined by a
fine one (`loop_candidates`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator

import numpy as np
from numpy.typing import NDArray

from scanguard.geometry import relative, transform_points
from scanguard.matching.correlative import correlative_match, match_to_map
from scanguard.matching.likelihood import LikelihoodGrid
from scanguard.scan import LaserScan
from scanguard.slam.graph.closure import ClosureCandidate
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.local_map import GraphNode
from scanguard.slam.graph.solver import PoseGraphSolver

_MAX_SUBMAPS = 64


class SubmapCache:
    """Coarse and fine likelihood grids of chain centres, least recently used dropped."""

    def __init__(self) -> None:
        self._maps: OrderedDict[int, tuple[LikelihoodGrid, LikelihoodGrid]] = OrderedDict()

    def clear(self) -> None:
        """Forget every submap (a closure moved the nodes they were built from)."""
        self._maps.clear()

    def get(
        self, centre: int, nodes: list[GraphNode], est: NDArray[np.float64], cfg: GraphConfig
    ) -> tuple[LikelihoodGrid, LikelihoodGrid]:
        """The (coarse, fine) submap of the chain around node ``centre``, in its frame."""
        cached = self._maps.get(centre)
        if cached is not None:
            self._maps.move_to_end(centre)
            return cached
        lo = max(0, centre - cfg.loop_submap_nodes)
        hi = min(len(nodes), centre + cfg.loop_submap_nodes + 1)
        parts = [
            transform_points(relative(est[centre], est[m]), nodes[m].outline)
            for m in range(lo, hi)
            if nodes[m].accepted
        ]
        pts = np.concatenate(parts)
        maps = (
            LikelihoodGrid.from_points(pts, cfg.loop_matcher),
            LikelihoodGrid.from_points(pts, cfg.loop_fine),
        )
        self._maps[centre] = maps
        if len(self._maps) > _MAX_SUBMAPS:
            self._maps.popitem(last=False)
        return maps


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


def candidate_chains(
    nodes: list[GraphNode],
    est: NDArray[np.float64],
    k: int,
    cfg: GraphConfig,
    index: NodeIndex | None = None,
) -> list[int]:
    """Centres of candidate chains for node ``k``, nearest first.

    ``index`` (kept by the caller across searches) saves re-reading every node's fields.
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
    mask &= dist <= cfg.loop_search_maximum_distance
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    centres = []
    for chain in np.split(idx, breaks):
        if len(chain) < cfg.loop_match_minimum_chain_size:
            continue
        centres.append(int(chain[np.argmin(dist[chain])]))
    centres.sort(key=lambda c: float(dist[c]))
    return centres[:2]


def loop_candidates(
    k: int,
    nodes: list[GraphNode],
    scans: list[LaserScan],
    solver: PoseGraphSolver,
    submaps: SubmapCache,
    cfg: GraphConfig,
    stats: dict[str, float],
    index: NodeIndex | None = None,
) -> Iterator[ClosureCandidate]:
    """The loop-closure candidates of node ``k``, one per chain that matches, nearest first.

    Lazily: the caller judges each candidate before the next chain is searched, and each
    search reads the solver's estimates as they are then (a refused closure may have
    rebuilt them).
    """
    node = nodes[k]
    for centre in candidate_chains(nodes, solver.est, k, cfg, index):
        stats["loop_searches"] += 1
        coarse_map, fine_map = submaps.get(centre, nodes, solver.est, cfg)
        initial = relative(solver.est[centre], solver.est[k])
        coarse = correlative_match(node.points, coarse_map, initial, cfg.loop_matcher)
        if not coarse.found or coarse.score < cfg.loop_min_response:
            continue
        m, fine = match_to_map(node.points, fine_map, coarse.pose, cfg.loop_fine)
        pose = np.asarray(m.pose if m.ok else fine.pose, dtype=np.float64)
        if not np.all(np.isfinite(pose)):
            continue
        yield ClosureCandidate(
            node=k,
            target_node=centre,
            scan_index=node.scan_index,
            target_scan_index=nodes[centre].scan_index,
            pose=pose,
            score=float(fine.score),
            coarse_score=float(coarse.score),
            covariance=np.asarray(fine.covariance, dtype=np.float64),
            source=scans[k],
            target=scans[centre],
            match=m,
            prior_pose=initial,
            path_gap=node.path - nodes[centre].path,
        )


__all__ = ["NodeIndex", "SubmapCache", "candidate_chains", "loop_candidates"]
