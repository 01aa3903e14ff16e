"""The pieces of a guarded loop that `scanguard run` and the live node build the same way.

`scanguard.apps.run` builds them from a whole recording; a live node
(`scanguard.apps.node`) from the first scan and the transforms it knows at that moment. Both
then feed the same `scanguard.slam.loop.RunLoop`, so a scan goes through one per-scan step.
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.pairs.labels import LabelConfig
from scanguard.runtime.streaming import discard_spare, prestart_worker
from scanguard.scan import LaserScan
from scanguard.slam.backend import Backend
from scanguard.slam.config import PROCESS_MIN_SCANS, RunConfig
from scanguard.slam.detached import (
    DETACHABLE,
    WORKER_WARM_UP,
    DetachedBackend,
    DetachedGroup,
    InstancesSpec,
)
from scanguard.slam.gate import Gate
from scanguard.slam.grid import GridConfig, build_map
from scanguard.slam.guard import ScanPairs
from scanguard.slam.judge import Judge
from scanguard.slam.loop import Instance, RunLoop, instance_gates
from scanguard.slam.registry import closure_judge_for, make_backend, needs_detector
from scanguard.slam.wheel_support import WheelSupport

logger = logging.getLogger(__name__)


def resolve_labels(cfg: RunConfig, detector: Any) -> None:
    """Label rule of the oracle: the detector's own thresholds unless the config sets one."""
    if cfg.labels is None:
        rule = getattr(detector, "label_thresholds", None)
        cfg.labels = LabelConfig.from_dict(dict(rule)) if rule else LabelConfig()


def adjust_without_odometry(name: str, cfg: RunConfig) -> None:
    """Make GMapping and the graph process scans without odometry (their triggers never fire).

    With ``motion: fused`` both back ends keep their travel triggers: they fire on the fused
    motion (the judged matches and the prediction). For GMapping, processing every scan was 4x
    slower on the hand-carried CCNY bag for the same map, and on a stationary scanner among
    walking people (``leg_tracker_positive_1.bag``) it let the walkers into the map (ATE 0.054 m
    against 0.011 m with the triggers; README, 2026-12-02). For the graph, a node at every scan
    measured worse than nodes on the fused travel on simulated scenes run without odometry and
    took twice as long on the CCNY bag (README, "Without odometry", session 11). The graph's
    prior still predicts worse than wheels would, so its sequential search widens either way.
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
        update: dict[str, object] = {"sequential": wide, "odometry_is_prior": True}
        if cfg.motion == "fused":
            what = "nodes follow the fused motion's travel"
        else:
            what = "every scan is a node (minimum_time_interval = 0)"
            update["minimum_time_interval"] = 0.0
        logger.warning(
            "%s: without odometry the graph's prior predicts badly: %s and the sequential "
            "search window widens to +-%.1f m, +-%.1f rad",
            name,
            what,
            wide.window_xy,
            wide.window_theta,
        )
        cfg.graph = cfg.graph.model_copy(update=update)


def prestart_instance_worker(cfg: RunConfig) -> None:
    """Start the worker process a long recording's instances will use, before it is read.

    A worker takes about a second to start, on the run's critical path when its instances are
    the slower half; started here, it loads its modules and kernels while the recording is
    read and the models load. Only where ``cfg`` would use one for a recording of
    `PROCESS_MIN_SCANS` scans; `build_instances` kills it when the recording turns out
    shorter (or the instances stay here).
    """
    if cfg.max_scans is not None and cfg.max_scans < PROCESS_MIN_SCANS:
        return
    if cfg.worker_processes(PROCESS_MIN_SCANS, 1) > 0:
        prestart_worker(WORKER_WARM_UP)


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
    n_scans: int = 0,
) -> dict[str, Instance]:
    """One back end per gate, from ``backend_factory`` or the registry.

    The comparison instances run in worker processes where ``cfg.worker_processes`` says so
    (never with a ``backend_factory``: a worker builds its back ends from the registry); with
    no comparison, the guarded instance does, where its back end needs no detector.

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
        n_scans: Scans of the recording (0: unknown, a stream: no worker processes).
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

    out: dict[str, Instance] = {}
    detach = [
        g for g in gates if g in DETACHABLE or (not cfg.compare and not needs_detector(cfg, g))
    ]
    workers = 0 if backend_factory is not None else cfg.worker_processes(n_scans, len(detach))
    if workers == 0:
        discard_spare()  # a worker started ahead for a recording that needs none
    for w in range(workers):
        mine = tuple(detach[w::workers])
        spec = InstancesSpec(cfg, mine, laser_offset, start, range_max, reference)
        group = DetachedGroup(spec)
        out.update({g: Instance(DetachedBackend(group, g), gates[g]) for g in mine})
    for g, gate in gates.items():
        if g not in out:
            out[g] = Instance(build(g), gate)
    return {g: out[g] for g in gates}  # the gates' order


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
        free_space=cfg.guard.free_space_history(cfg.free_space_horizon()),
        wheel_support=WheelSupport(laser_offset) if cfg.wheel_support() else None,
    )


def map_source(
    backend: Any,
    scans: list[LaserScan],
    laser_offset: NDArray[np.float64],
    grid: GridConfig,
) -> Callable[[], tuple[NDArray[np.float64], Any]]:
    """A function giving ``backend``'s trajectory and map as they are now, from copies.

    Cheap to call (between two scans); the function it returns does the work, and may run on
    another thread while the back end goes on. GMapping (``map_builder``): its history, the
    trajectory and the map computed when called. A back end that keeps its map (``grid()``):
    copies of both. One without (``grid()`` is None, the graph): the map built from
    ``scans`` (the node keeps them) as `scanguard.apps.run_report.instance_grid` builds it.
    """
    builder = getattr(backend, "map_builder", None)
    if builder is not None:
        out: Callable[[], tuple[NDArray[np.float64], Any]] = builder()
        return out
    traj = np.asarray(backend.trajectory(), dtype=np.float64).reshape(-1, 3).copy()
    kept = backend.grid()
    if kept is not None:
        snap = copy.deepcopy(kept)
        return lambda: (traj, snap)
    scans, used = list(scans), np.asarray(backend.used(), dtype=bool)
    return lambda: (traj, build_map(scans, traj, laser_offset, include=used, config=grid))


def warm_up(cfg: RunConfig, detector: Any, baseline: Any, matcher: Any = None) -> float:
    """Run the loop once over a few synthetic scans (kernels load before a node's first scan).

    Returns:
        The seconds it took.
    """
    from scanguard.matching import get_matcher

    t0 = time.perf_counter()
    cfg = cfg.model_copy(deep=True)
    resolve_labels(cfg, detector)
    if cfg.motion != "guarded_matches":
        adjust_without_odometry("warm-up", cfg)
    angles = np.linspace(-2.0, 2.0, 400)
    offset = np.zeros(3)
    gates = instance_gates(cfg, ["cnn"], detector, baseline)
    inst = build_instances(
        cfg, gates, detector, laser_offset=offset, start=np.zeros(3), range_max=10.0
    )
    m = matcher if matcher is not None else get_matcher(cfg.matcher)
    loop = RunLoop(
        inst, scan_pairs(cfg, m, detector, baseline, offset), cfg, odometry=None, start=np.zeros(3)
    )
    loop.begin()
    for k in range(4):  # a 4 m square room seen from near its middle, the robot creeping
        side = 2.0 - 0.02 * k
        r = side / np.maximum(np.abs(np.cos(angles)), np.abs(np.sin(angles)))
        loop.feed(LaserScan(0.1 * k, r.astype(np.float32), -2.0, 4.0 / 399, 0.05, 10.0))
    inst["cnn"].backend.grid()
    import matplotlib.image  # noqa: F401  (the PNG writer of the map saved at exit)

    return time.perf_counter() - t0
