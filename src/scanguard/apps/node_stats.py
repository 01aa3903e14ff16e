"""The counts and timings of a live node (`scanguard.apps.node`): its log line and status."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class NodeStats:
    """Counters, per-scan latency (receive -> processed) and step (the loop's step alone)."""

    received: int = 0
    dropped: int = 0
    throttled: int = 0
    processed: int = 0
    no_odometry: int = 0
    failed: int = 0
    latency: list[float] = field(default_factory=list)
    step: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """Counts, latency and step median / p99 / max (ms; None before any scan)."""
        return {
            "received": self.received,
            "processed": self.processed,
            "dropped": self.dropped,
            "throttled": self.throttled,
            "skipped_no_odometry": self.no_odometry,
            "failed": self.failed,
            "latency_ms": _spread(self.latency),
            "step_ms": _spread(self.step),
        }

    def line(self) -> str:
        """The summary as one log line."""
        s = self.summary()
        lat = s["latency_ms"]
        text = (
            f"scans: {s['received']} received, {s['processed']} processed, {s['dropped']} "
            f"dropped (queue full)"
        )
        if s["skipped_no_odometry"] or s["failed"]:
            text += f", {s['skipped_no_odometry']} without odometry, {s['failed']} failed"
        if lat["median"] is not None:
            text += (
                f"; latency receive -> processed: median {lat['median']:.1f} ms, "
                f"p99 {lat['p99']:.1f} ms, max {lat['max']:.1f} ms (step alone: median "
                f"{s['step_ms']['median']:.1f} ms, p99 {s['step_ms']['p99']:.1f} ms)"
            )
        return text


def _spread(seconds: list[float]) -> dict[str, float | None]:
    ms = 1e3 * np.asarray(seconds, dtype=np.float64)
    if not ms.size:
        return {"median": None, "p99": None, "max": None}
    return {
        "median": float(np.median(ms)),
        "p99": float(np.percentile(ms, 99)),
        "max": float(np.max(ms)),
    }
