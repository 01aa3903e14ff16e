"""What the ``graph`` back end keeps per node and per submap: bounded, the same results.

Issue 32 item 3 / issue 28 item 5: three graph instances that each kept every node's float64
points and outline, and up to 64 submaps of up to 70 MB, peaked at 1.7 GB on ACES.
"""

from __future__ import annotations

import numpy as np
import pytest

from scanguard.slam.graph import ClosureCandidate, GraphBackend, GraphConfig
from scanguard.slam.graph.closure import ClosureVerdict
from scanguard.slam.graph.local_map import GraphNode
from scanguard.slam.graph.loop_search import SubmapCache, grid_bytes
from tests.test_graph import SICK, ring  # noqa: F401 (fixture)


class EveryFourth:
    """Accepts one candidate in four: searches go on between closures, submaps are reused."""

    name = "every-fourth"

    def __init__(self) -> None:
        self.seen = 0

    def __call__(self, candidate: ClosureCandidate) -> ClosureVerdict:
        self.seen += 1
        return ClosureVerdict(self.seen % 4 == 0, candidate.score, self.name)


def _run(ring, config: GraphConfig, *, submap_bytes: int, keep_all: bool = False):  # type: ignore[no-untyped-def]  # noqa: F811
    ref, scans, odo = ring
    b = GraphBackend(
        config, initial_pose=ref[0], range_max=SICK.range_max, closure_judge=EveryFourth()
    )
    b._submaps.max_bytes = submap_bytes
    for i, s in enumerate(scans):
        b.update(s, odo[i], usable=not 0.6 * len(scans) <= i < 0.85 * len(scans))
        if keep_all:  # the reference: every node holds its arrays, as before
            for node in b._nodes:
                node.hold()
    return b


@pytest.fixture(scope="module")
def runs(ring):  # type: ignore[no-untyped-def]  # noqa: F811
    """The compact back end (no submap grid kept) and the reference that keeps everything."""
    # closures enter as the arbitrary judge says, none waiting for confirmation or refused as
    # too far (the drifted ring's closures claim metres)
    cfg = GraphConfig(closure_confirm_sigmas=None, closure_far_sigmas=None)
    compact = _run(ring, cfg, submap_bytes=0)
    reference = _run(ring, cfg, submap_bytes=2**40, keep_all=True)
    return compact, reference


def test_compact_storage_gives_the_same_graph_as_keeping_everything(runs) -> None:  # type: ignore[no-untyped-def]
    compact, reference = runs
    assert compact.stats["loop_searches"] >= 10 and compact.stats["closures_accepted"] >= 1
    np.testing.assert_array_equal(compact.trajectory(), reference.trajectory())
    np.testing.assert_array_equal(
        compact.node_poses(optimized=False), reference.node_poses(optimized=False)
    )
    assert [c.candidate.node for c in compact.closures] == [
        c.candidate.node for c in reference.closures
    ]
    # the compact one rebuilt the submaps searched again (from their recipes), the other not
    assert compact._submaps.builds > reference._submaps.builds
    assert compact._submaps.held_bytes == 0


def test_only_the_next_local_map_holds_its_arrays(runs) -> None:  # type: ignore[no-untyped-def]
    compact, reference = runs
    nodes: list[GraphNode] = compact._nodes
    held = [k for k, n in enumerate(nodes) if n.held]
    accepted = [k for k, n in enumerate(nodes) if n.accepted]
    n_local = compact.config.local_map_nodes
    assert len(nodes) > 4 * n_local
    assert held == accepted[-n_local:]  # the newest accepted nodes, nothing else
    assert not any(n.held for n in nodes if not n.accepted)
    assert not hasattr(nodes[0], "__dict__")  # slotted
    # per scan: numpy buffers (24 + 8 + 1 bytes), not lists of small arrays and boxed numbers
    n_scans = len(reference.trajectory())
    assert compact._scan_odom.values.shape == (n_scans, 3)
    assert compact._scan_node.values.dtype == np.int64 and compact.used().dtype == np.bool_
    # a released node derives its arrays again, bit for bit those it held, and keeps none
    for k in (0, len(nodes) // 2, held[0] - 1):
        want = reference._nodes[k].geometry()
        got = nodes[k].geometry()
        assert not nodes[k].held
        assert got.points.dtype == np.float64 and got.outline.dtype == np.float64
        np.testing.assert_array_equal(got.points, want.points)
        np.testing.assert_array_equal(got.outline, want.outline)
        assert got.points is not want.points
        assert nodes[k].scan is reference._nodes[k].scan  # the recording's scan, not a copy


def test_a_held_node_places_its_outline_once_per_estimate(runs) -> None:  # type: ignore[no-untyped-def]
    """The placed outline is reused while the estimate is the same bit for bit, never after."""
    from scanguard.geometry import transform_points

    compact, _ = runs
    nodes: list[GraphNode] = compact._nodes
    k = next(k for k, n in enumerate(nodes) if n.held)
    node, pose = nodes[k], compact._est[k].copy()
    first = node.placed_outline(pose)
    np.testing.assert_array_equal(first, transform_points(pose, node.outline))
    assert not first.flags.writeable  # shared between local maps: never written
    assert node.placed_outline(pose.copy()) is first  # same bits: the same array
    moved = pose + np.array([0.0, 0.0, 1e-12])
    second = node.placed_outline(moved)
    assert second is not first
    np.testing.assert_array_equal(second, transform_points(moved, node.outline))
    node.release()  # a released node keeps nothing placed
    assert node.placed_outline(moved) is not node.placed_outline(moved)
    node.hold()


def test_the_submap_cache_keeps_its_grids_within_its_byte_budget(ring) -> None:  # type: ignore[no-untyped-def]  # noqa: F811
    b = _run(ring, GraphConfig(loop_closure=False), submap_bytes=0)
    cfg = b.config
    centres = [c for c in range(10, len(b._nodes) - 10, 7) if b._nodes[c].accepted][:6]
    one = grid_bytes(SubmapCache().get(centres[0], b._nodes, b._est, cfg))
    cache = SubmapCache(max_bytes=int(2.5 * one))
    first = {c: cache.get(c, b._nodes, b._est, cfg) for c in centres}
    assert cache.builds == len(centres) and cache.held_bytes <= cache.max_bytes
    # moved estimates do not change a remembered submap: its recipe fixed the poses
    moved = b._est + np.array([0.3, -0.2, 0.05])
    again = cache.get(centres[0], b._nodes, moved, cfg)  # dropped: rebuilt from its recipe
    assert cache.builds == len(centres) + 1
    for a, f in zip(again, first[centres[0]], strict=True):
        np.testing.assert_array_equal(a.stack, f.stack)
        assert a.origin == f.origin
    assert cache.get(centres[0], b._nodes, moved, cfg) is again  # the newest one is held
    cache.clear()
    assert cache.held_bytes == 0
    fresh = cache.get(centres[0], b._nodes, moved, cfg)
    assert fresh[0].origin != first[centres[0]][0].origin  # cleared: built from the new poses


@pytest.mark.parametrize("carve", [4])
def test_carving_views_derived_again_give_the_same_trajectory(carve: int) -> None:
    from tests.helpers import pace_walk

    scans, poses = pace_walk(51)
    trajs = []
    for keep_all in (False, True):
        g = GraphBackend(GraphConfig(loop_closure=False, carve_frames=carve, local_map_nodes=6))
        for scan, pose in zip(scans, poses, strict=True):
            g.update(scan, pose)
            if keep_all:
                for node in g._nodes:
                    node.hold()
        assert g.stats["moving_points_left_out"] > 0
        assert sum(n.held for n in g._nodes) == (len(g._nodes) if keep_all else 6)
        trajs.append(g.trajectory())
    np.testing.assert_array_equal(trajs[0], trajs[1])
