"""The pieces of a guarded loop that `scanguard run` and the live node build the same way.

`scanguard.apps.run` builds them from a whole recording; a live node
(`scanguard.apps.node`) from the first scan and the transforms it knows at that moment. Both
then feed the same `scanguard.slam.loop.RunLoop`, so a scan goes through one per-scan step.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.pairs.labels import LabelConfig
from scanguard.slam.backend import Backend
from scanguard.slam.config import RunConfig
from scanguard.slam.gate import Gate
from scanguard.slam.guard import ScanPairs
from scanguard.slam.judge import Judge
from scanguard.slam.loop import Instance
from scanguard.slam.registry import closure_judge_for, make_backend

logger = logging.getLogger(__name__)


def resolve_labels(cfg: RunConfig, detector: Any) -> None:
    """Label rule of the oracle: the detector's own thresholds unless the config sets one."""
    if cfg.labels is None:
        rule = getattr(detector, "label_thresholds", None)
        cfg.labels = LabelConfig.from_dict(dict(rule)) if rule else LabelConfig()


def adjust_without_odometry(name: str, cfg: RunConfig) -> None:
    """Make GMapping and the graph process scans without odometry (their triggers never fire).

    With ``motion: fused`` GMapping's travel triggers fire on the fused motion (the judged
    matches and the prediction), so it keeps them: processing every scan was 4x slower on the
    hand-carried CCNY bag for the same map, and on a stationary scanner among walking people
    (``leg_tracker_positive_1.bag``) it let the walkers into the map (ATE 0.054 m against
    0.011 m with the triggers; README, 2026-12-02).
    """
    if cfg.backend == "gmapping" and cfg.gmapping.temporalUpdate < 0 and cfg.motion != "fused":
        logger.warning(
            "%s: without odometry GMapping's linearUpdate/angularUpdate never trigger: "
            "setting temporalUpdate = 0 (process every scan)",
            name,
        )
        cfg.gmapping = cfg.gmapping.model_copy(update={"temporalUpdate": 0.0})
    if cfg.backend == "graph" and cfg.graph.minimum_time_interval < 0:
        seq_m = cfg.graph.sequential
        wide = seq_m.model_copy(
            update={
                "window_xy": max(seq_m.window_xy, 1.5),
                "window_theta": max(seq_m.window_theta, 0.8),
                "levels": max(seq_m.levels, 6),
            }
        )
        logger.warning(
            "%s: without odometry the graph's travel triggers never fire and its prior "
            "predicts badly: every scan is a node (minimum_time_interval = 0) and the "
            "sequential search window widens to +-%.1f m, +-%.1f rad",
            name,
            wide.window_xy,
            wide.window_theta,
        )
        cfg.graph = cfg.graph.model_copy(
            update={"minimum_time_interval": 0.0, "sequential": wide, "odometry_is_prior": True}
        )


def build_instances(
    cfg: RunConfig,
    gates: dict[str, Gate],
    detector: Any,
    *,
    laser_offset: NDArray[np.float64],
    start: NDArray[np.float64],
    range_max: float | None,
    reference: NDArray[np.float64] | None = None,
    backend_factory: Callable[[], Backend] | None = None,
) -> dict[str, Instance]:
    """One back end per gate, from ``backend_factory`` or the registry.

    Args:
        cfg: The resolved settings.
        gates: Gate name -> its gate (`scanguard.slam.loop.instance_gates`).
        detector: The CNN fault detector (a graph back end's closure judge may use it).
        laser_offset: Pose of the laser in the robot frame.
        start: Robot pose of the first scan.
        range_max: The sensor's largest range (m), or None.
        reference: Reference robot poses (the oracle closure judge), or None.
        backend_factory: Builds one identical, independent back end per call (default: the
            registry's back end of ``cfg.backend``).
    """

    def build(gate: str) -> Backend:
        if backend_factory is not None:
            return backend_factory()
        return make_backend(
            cfg,
            laser_offset=laser_offset,
            initial_pose=start,
            range_max=range_max,
            closure_judge=closure_judge_for(cfg, gate, detector, laser_offset, reference),
            reference=reference,
        )

    return {g: Instance(build(g), gate) for g, gate in gates.items()}


def scan_pairs(
    cfg: RunConfig,
    matcher: Any,
    detector: Any,
    baseline: Any,
    laser_offset: NDArray[np.float64],
) -> ScanPairs:
    """The matcher and the judge of consecutive scans, as the settings ask."""
    return ScanPairs(
        matcher,
        Judge(
            detector,
            baseline,
            laser_offset=laser_offset,
            use_odometry=cfg.judge_reads_odometry(),
            odometry_below_eig=cfg.guard.odometry_below_eig,
        ),
        min_points=cfg.guard.min_points,
        odometry_initial_guess=cfg.guard.odometry_initial_guess,
        laser_offset=laser_offset,
    )
