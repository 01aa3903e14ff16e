"""Search lanes: one branch-and-bound search split over threads, with the same result.

A wide correlative search (a loop closure's: thousands of coarse candidates, 5-100 ms) is the
largest single piece of a graph instance's work, and where the instance runs alone in a worker
process the second core idles once the guard is done with the recording. `set_search_lanes`
lets the searches of this process use it: the coarse scores are filled half by each thread
(`_correlative.top_sums`), the roots are sorted once, and each lane searches every other root
best first (`_correlative.descend`), skipping what scores below the other lane's best so far.
The merge takes the highest score, a tie going to the root first in the sorted order, which is
the leaf the one-lane search returns: results are the same bit for bit (tested against it).

The kernels release the GIL; a search of a few hundred coarse candidates costs less than
handing half of it to a thread, so such searches stay on one lane.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

import scanguard.matching._correlative as _k

#: Searches with fewer coarse candidates than this stay on one lane (a sequential match to
#: the local map has ~100-900, a loop search ~1000-10000; a thread hand-off costs ~50 us).
MIN_LANE_CANDIDATES = 1000

_lock = threading.Lock()
_lanes = 1
_pool: ThreadPoolExecutor | None = None

#: ``(k, dx, dy, best_sum, n_evaluated, found)`` of a search (`_correlative.branch_and_bound`)
Found = tuple[int, int, int, float, int, bool]


def set_search_lanes(lanes: int) -> None:
    """Split each wide search of this process over ``lanes`` threads (1: never)."""
    global _lanes, _pool
    with _lock:
        _lanes = max(1, int(lanes))
        if _pool is not None and _lanes == 1:
            _pool.shutdown(wait=False)
            _pool = None


def search_lanes() -> int:
    """The lanes a wide search of this process uses."""
    return _lanes


def _helper() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scanguard-search")
        return _pool


def branch_and_bound(
    stack: NDArray[np.float32],
    pad: int,
    runs: tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.float64], NDArray[np.int64]],
    w: int,
    levels: int,
    threshold: float,
    exclude: tuple[int, int, float] = (0, 0, -1.0),
) -> Found:
    """`_correlative.branch_and_bound` over the merged ``runs``, on two lanes when asked."""
    ix, iy, wt, count = runs
    m = (2 * w) // (1 << (levels - 1)) + 1
    k_n = ix.shape[0]
    n_top = k_n * m * m
    if _lanes < 2 or n_top < MIN_LANE_CANDIDATES or k_n < 2:
        return _k.branch_and_bound(stack, pad, ix, iy, wt, count, w, levels, threshold, *exclude)
    pool = _helper()
    cs = np.empty(n_top, dtype=np.float64)
    half = k_n // 2
    other = pool.submit(_k.top_sums, stack, pad, ix, iy, wt, count, w, levels, half, k_n, cs)
    _k.top_sums(stack, pad, ix, iy, wt, count, w, levels, 0, half, cs)
    other.result()
    order = _k.sort_order(cs)
    shared = np.full(2, -np.inf)
    args = (stack, pad, ix, iy, wt, count, w, levels, threshold, *exclude, cs, order)
    second = pool.submit(_k.descend, *args, 1, shared)
    lanes = [_k.descend(*args, 0, shared), second.result()]
    n_eval = n_top + sum(int(r[4]) for r in lanes)
    found = [r for r in lanes if r[5]]
    if not found:
        return 0, 0, 0, threshold, n_eval, False
    # the highest score; a tie to the root searched first (the larger position in the order)
    k, dx, dy, best, _, _, _ = max(found, key=lambda r: (r[3], r[6]))
    return int(k), int(dx), int(dy), float(best), n_eval, True


__all__ = [
    "MIN_LANE_CANDIDATES",
    "branch_and_bound",
    "search_lanes",
    "set_search_lanes",
]
