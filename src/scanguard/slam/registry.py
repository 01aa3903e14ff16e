"""The registry of SLAM back ends: name -> factory (``frontend``, ``gmapping``, ``graph``).

A factory builds one fresh back end from the run settings; every call gives an identical,
independent instance (the loop runs one per gate). `register_backend` adds another.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scanguard.errors import ConfigError, ModelError
from scanguard.geometry import compose
from scanguard.slam.backend import Backend, FrontendBackend
from scanguard.slam.config import RunConfig


@dataclass(frozen=True)
class BackendSetup:
    """What a back end needs to know of the recording and the instance it is built for.

    Attributes:
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose of the first scan.
        range_max: The sensor's maximum range (m), for GMapping's ``maxRange``.
        closure_judge: ``graph`` only: the loop-closure judge
            (`scanguard.slam.graph.closure.ClosureJudge`; None = accept all).
        reference: ``graph`` only: reference robot poses, to label closure candidates in the
            report (never used for estimation).
    """

    laser_offset: Any = (0.0, 0.0, 0.0)
    initial_pose: Any = (0.0, 0.0, 0.0)
    range_max: float | None = None
    closure_judge: Any = None
    reference: Any = None


BackendFactory = Callable[[RunConfig, BackendSetup], Backend]


def gmapping_backend_class() -> type | None:
    """`scanguard.slam.gmapping.GMappingBackend`, or None where this build lacks it."""
    try:
        import scanguard.slam.gmapping as gm
    except ImportError:
        return None
    cls = getattr(gm, "GMappingBackend", None)
    return cls if isinstance(cls, type) else None


def _graph(config: RunConfig, setup: BackendSetup) -> Backend:
    from scanguard.slam.graph import GraphBackend
    from scanguard.slam.graph.closure import AcceptAll

    judge = setup.closure_judge
    judged = judge is not None and not isinstance(judge, AcceptAll)
    return GraphBackend(
        config.graph_settings(judged=judged),
        laser_offset=setup.laser_offset,
        initial_pose=setup.initial_pose,
        range_max=setup.range_max,
        closure_judge=setup.closure_judge,
        reference=setup.reference,
    )


def _frontend(config: RunConfig, setup: BackendSetup) -> Backend:
    return FrontendBackend(
        laser_offset=setup.laser_offset,
        initial_pose=setup.initial_pose,
        motion_prior="constant_velocity"
        if config.prior == "constant_velocity"
        else "constant_position",
        grid=config.guard.grid,
    )


def _gmapping(config: RunConfig, setup: BackendSetup) -> Backend:
    cls = gmapping_backend_class()
    if cls is None:
        raise ConfigError(
            "the gmapping back end (scanguard.slam.gmapping.GMappingBackend) is not available "
            "in this build: use --backend frontend"
        )
    backend: Backend = cls(
        config.gmapping,
        laser_offset=tuple(float(v) for v in np.asarray(setup.laser_offset).reshape(3)),
        initial_pose=tuple(float(v) for v in np.asarray(setup.initial_pose).reshape(3)),
        range_max=setup.range_max,
    )
    return backend


#: Back-end name -> factory.
BACKENDS: dict[str, BackendFactory] = {
    "gmapping": _gmapping,
    "frontend": _frontend,
    "graph": _graph,
}


def register_backend(name: str, factory: BackendFactory) -> None:
    """Make ``factory`` the back end called ``name`` (replacing one of that name)."""
    BACKENDS[name] = factory


def make_backend(
    config: RunConfig,
    *,
    laser_offset: Any = (0.0, 0.0, 0.0),
    initial_pose: Any = (0.0, 0.0, 0.0),
    range_max: float | None = None,
    closure_judge: Any = None,
    reference: Any = None,
) -> Backend:
    """A fresh back end of ``config.backend`` (every call gives an identical, independent one).

    Args:
        config: Run settings (``backend``, ``gmapping``, ``graph``, ``prior``, ``guard.grid``).
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose of the first scan.
        range_max: The sensor's maximum range (m), for GMapping's ``maxRange``.
        closure_judge: ``graph`` only: the loop-closure judge (None = accept all).
        reference: ``graph`` only: reference robot poses (report labels only).

    Raises:
        ConfigError: The back end is unknown or not available in this build.
    """
    factory = BACKENDS.get(config.backend)
    if factory is None:
        raise ConfigError(
            f"unknown back end {config.backend!r}: use one of {', '.join(sorted(BACKENDS))}"
        )
    setup = BackendSetup(laser_offset, initial_pose, range_max, closure_judge, reference)
    return factory(config, setup)


def needs_detector(config: RunConfig, gate: str) -> bool:
    """Whether ``gate``'s back end reads the CNN detector (then it cannot leave this process).

    Only the graph's ``cnn`` closure judge does, and only without a learned closure-judge file
    (`scanguard.slam.graph.judges.judge_for_gate`).
    """
    if config.backend != "graph" or gate != "cnn":
        return False
    from scanguard.slam.graph.judges import default_judge_path

    named = config.graph.closures.judge_file
    return not (default_judge_path() if named is None else Path(named)).is_file()


def closure_judge_for(
    config: RunConfig, gate: str, detector: Any, laser_offset: Any, reference: Any
) -> Any:
    """The loop-closure judge of a gate's ``graph`` instance (None for other back ends)."""
    if config.backend != "graph":
        return None
    from scanguard.slam.graph.judges import judge_for_gate

    ref_sensor = None if reference is None else compose(reference, laser_offset)
    closures = config.graph.closures
    if closures.judge_file is not None and not Path(closures.judge_file).is_file():
        # named on purpose: never fall back to another judge in silence
        raise ModelError(f"{closures.judge_file}: closure-judge file not found")
    return judge_for_gate(
        gate,
        closures,
        detector=detector,
        reference_sensor=ref_sensor,
        judge_file=closures.judge_file,
    )
