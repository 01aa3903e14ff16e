"""`FinishedGraph`: a graph back end's results once its recording is over, without the solver.

What `GraphBackend.snapshot` gives a caller in another process (`scanguard.slam.detached`):
besides `scanguard.slam.backend.FinishedBackend`'s trajectory, used scans and stats, what the
graph's writers read (``closures_<instance>.csv``, ``graph.png``): the closure records, the
edges, the optimised node poses and the name of the closure judge.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from scanguard.slam.backend import FinishedBackend
from scanguard.slam.graph.closure import ClosureJudge, ClosureRecord


class _Graph(Protocol):
    """What `FinishedGraph.of_graph` reads of a `GraphBackend` (which imports this module)."""

    closures: list[ClosureRecord]
    edges: list[tuple[int, int, str]]
    stats: dict[str, float]
    closure_judge: ClosureJudge

    @property
    def name(self) -> str: ...

    @property
    def pose(self) -> NDArray[np.float64]: ...

    def trajectory(self) -> NDArray[np.float64]: ...

    def used(self) -> NDArray[np.bool_]: ...

    def grid(self) -> Any: ...

    def node_poses(self, *, optimized: bool = True) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class JudgeName:
    """The closure judge of a finished graph, as reports name it."""

    name: str


@dataclass
class FinishedGraph(FinishedBackend):
    """`FinishedBackend` of a `GraphBackend`, with its graph (see the module docstring).

    Attributes:
        closures: `GraphBackend.closures`.
        edges: `GraphBackend.edges`.
        nodes: `GraphBackend.node_poses` (optimised when the graph batch-optimises).
        closure_judge: The name of its closure judge.
    """

    closures: list[ClosureRecord] = field(default_factory=list)
    edges: list[tuple[int, int, str]] = field(default_factory=list)
    nodes: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    closure_judge: JudgeName = field(default_factory=lambda: JudgeName("none"))

    @classmethod
    def of_graph(cls, graph: _Graph) -> FinishedGraph:
        """``graph``'s results as they are now (its batch pass runs here when it has one)."""
        poses = graph.trajectory()  # first: its batch pass fills the stats' time
        return cls(
            name=graph.name,
            final_pose=graph.pose,
            poses=poses,
            used_mask=graph.used(),
            final_grid=graph.grid(),
            stats=dict(graph.stats),
            closures=list(graph.closures),
            edges=list(graph.edges),
            nodes=graph.node_poses(),
            closure_judge=JudgeName(str(graph.closure_judge.name)),
        )

    def node_poses(self, *, optimized: bool = True) -> NDArray[np.float64]:
        """The node sensor poses ``(M, 3)`` at the end (``optimized`` as the graph had them)."""
        return self.nodes.copy()
