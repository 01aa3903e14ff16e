"""Dynamic-environment 2D LiDAR simulator: crowded worlds with glass and mirrors, exact truth.

``simulate("corridor", seed=3, duration=120)`` returns a `ScanSequence` with scans, drifting
wheel odometry and exact ground-truth poses. Built-in scenarios mirror the paper's
Environments 1-4 (`lobby`, `corridor`, `glass`, `hall`) and 5 (`office`).
"""

from scanguard.sim.config import SENSOR_PRESETS, ScenarioConfig
from scanguard.sim.engine import (
    SCENARIOS,
    SimulationResult,
    apply_overrides,
    load_scenario,
    simulate,
    simulate_run,
)
from scanguard.sim.raycast import cast_rays, measure
from scanguard.sim.world import World, build_world

__all__ = [
    "SCENARIOS",
    "SENSOR_PRESETS",
    "ScenarioConfig",
    "SimulationResult",
    "World",
    "apply_overrides",
    "build_world",
    "cast_rays",
    "load_scenario",
    "measure",
    "simulate",
    "simulate_run",
]
