"""Pose-graph back end speed: one graph instance on a real log, reference vs current paths.

Workload: the first ``--max-scans`` scans of a Freiburg benchmark log (``--log``, default
Intel) fed straight to a `GraphBackend` (default settings, the log's wheel odometry, every
scan usable: no guard, no comparison instances), as one instance of ``scanguard run`` does.

Three paths are timed in the same process, alternately (``--rounds`` each, the fastest
kept, so that other jobs on the machine bias them alike):

- ``reference``: the code as it was before session 10's speed work, patched back in:
  the two ICP refinement starts as two separate matches (each building the local map's
  search structures), the grid's bounding box by numpy's ``min(axis=0)`` / ``max(axis=0)``,
  the loop search re-reading every node's path and flag at each search, and iSAM2 testing
  every variable for relinearization (``partial_relinearization=False``);
- ``exact``: the current code with ``partial_relinearization=False``: the same trajectory
  as ``reference`` bit for bit (checked; the run fails otherwise);
- ``current``: the current defaults. The partial relinearization check changes the
  estimates (printed: the largest node-pose difference from ``reference`` before the batch
  pass); its accuracy is measured on whole logs by ``scanguard run`` (benchmarks/README.md).

Printed per path: the back end's own phase timers (sequential match, iSAM2, loop search),
the whole update time and per node, and the ratio reference / path.

Run: python benchmarks/bench_graph.py [--log intel] [--max-scans 2000] [--rounds 1]
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

import scanguard.matching.likelihood as likelihood
import scanguard.slam.graph.local_map as local_map
from scanguard.io import read_sequence
from scanguard.matching.icp import match
from scanguard.slam.graph import GraphBackend, GraphConfig
from scanguard.slam.graph.loop_search import NodeIndex

BENCH = Path(__file__).resolve().parents[2] / "shared" / "data" / "benchmark"
PHASES = ("time_match_s", "time_isam_s", "time_loop_s")
PATHS = ("reference", "exact", "current")


def _separate_starts(method: Any, src: Any, tgt: Any, starts: Any, cfg: Any) -> list[Any]:
    return [match(method, src, tgt, s, cfg) for s in starts]


class _NumpyBounds:
    """The `_correlative` module with numpy's bounding box (what `from_points` did before)."""

    def __init__(self, kernels: Any) -> None:
        self._k = kernels

    def __getattr__(self, name: str) -> Any:
        return getattr(self._k, name)

    @staticmethod
    def bounds(pts: np.ndarray) -> tuple[float, float, float, float]:
        lo = pts.min(axis=0)
        hi = pts.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _rebuilt_arrays(self: NodeIndex, nodes: list[Any], n: int) -> tuple[np.ndarray, np.ndarray]:
    path = np.array([nodes[i].path for i in range(n)])
    acc = np.array([nodes[i].accepted for i in range(n)])
    return path, acc


@contextlib.contextmanager
def reference_path() -> Iterator[None]:
    """Patch the pre-session-10 code paths in (see the module docstring)."""
    saved = (local_map.match_starts, likelihood._k, NodeIndex.arrays)
    local_map.match_starts = _separate_starts  # type: ignore[assignment]
    likelihood._k = _NumpyBounds(saved[1])  # type: ignore[assignment]
    NodeIndex.arrays = _rebuilt_arrays  # type: ignore[method-assign]
    try:
        yield
    finally:
        local_map.match_starts, likelihood._k, NodeIndex.arrays = saved  # type: ignore[assignment]


def replay(seq: Any, *, partial: bool = True) -> tuple[dict[str, float], np.ndarray]:
    """Feed every scan to a fresh back end; its phase timers, wall time and node poses."""
    odom = np.asarray(seq.odometry, dtype=np.float64)
    cfg = GraphConfig(partial_relinearization=partial)
    backend = GraphBackend(cfg, range_max=float(seq.sensor.range_max))
    t0 = time.perf_counter()
    for scan, o in zip(seq.scans, odom, strict=True):
        backend.update(scan, o)
    wall = time.perf_counter() - t0
    stats = {p: float(backend.stats[p]) for p in PHASES}
    stats["update_s"] = wall
    stats["nodes"] = float(backend.stats["nodes"])
    return stats, backend.node_poses(optimized=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", default="intel", choices=["intel", "fr079", "aces"])
    ap.add_argument("--max-scans", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    seq = read_sequence(BENCH / f"{args.log}.clf.gz", max_scans=args.max_scans)
    replay(seq.subsequence(slice(0, 60)))  # warm-up: numba caches, gtsam
    best: dict[str, dict[str, float]] = {}
    poses: dict[str, np.ndarray] = {}
    for _ in range(args.rounds):
        for name in PATHS:
            ctx = reference_path() if name == "reference" else contextlib.nullcontext()
            with ctx:
                stats, est = replay(seq, partial=name == "current")
            poses[name] = est
            old = best.get(name)
            best[name] = stats if old is None else {k: min(v, old[k]) for k, v in stats.items()}
    _report(args, len(seq.scans), best, poses)


def _report(
    args: argparse.Namespace,
    scans: int,
    best: dict[str, dict[str, float]],
    poses: dict[str, np.ndarray],
) -> None:
    ref = best["reference"]
    nodes = {k: int(v["nodes"]) for k, v in best.items()}
    print(f"{args.log}, {scans} scans, nodes {nodes}; fastest of {args.rounds} round(s)")
    print(f"{'phase (s)':<16}" + "".join(f"{p:>11}{'ratio':>7}" for p in PATHS))
    for key in (*PHASES, "update_s"):
        cells = "".join(
            f"{best[p][key]:>11.2f}{ref[key] / max(best[p][key], 1e-9):>7.2f}" for p in PATHS
        )
        print(f"{key:<16}{cells}")
    per = "".join(f"{1e3 * best[p]['update_s'] / max(nodes[p], 1):>11.2f}{'':>7}" for p in PATHS)
    print(f"{'ms per node':<16}{per}")
    same = np.array_equal(poses["reference"], poses["exact"])
    print(f"exact == reference node poses: {same}")
    cur, old = poses["current"], poses["reference"]
    if cur.shape == old.shape:
        d = np.abs(cur - old)
        d[:, 2] = np.abs(np.angle(np.exp(1j * (cur[:, 2] - old[:, 2]))))
        print(f"current vs reference (before the batch pass): max |dxy| {d[:, :2].max():.3f} m")
    else:
        print(f"current vs reference: {cur.shape[0]} vs {old.shape[0]} nodes")
    if not same:
        raise SystemExit("the exact path changed the trajectory")


if __name__ == "__main__":
    main()
