"""`Rows` moved to `scanguard.slam.rows` (the graph back end keeps its per-scan numbers too)."""

from scanguard.slam.rows import Rows

__all__ = ["Rows"]
