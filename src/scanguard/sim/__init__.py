"""Dynamic-environment 2D LiDAR simulator: crowded worlds with glass and mirrors, exact truth.

``simulate("corridor", seed=3, duration=120)`` returns a `ScanSequence` with scans, drifting
wheel odometry and exact ground-truth poses. Built-in scenarios mirror the paper's
Environments 1-4 (`lobby`, `corridor`, `glass`, `hall`) and 5 (`office`); `GMAPPING_TRAPS`
(`crowd_stop`, `crowd_follow`, `long_corridor`, `glass_hall`, `mixed_loop`) are loops where a
particle-filter SLAM back end itself fails; `CLOSURE_TRAPS` (`twin_rooms`, `twin_corridors`,
`crowd_closure`) are loops where a pose-graph back end that accepts every loop closure folds its
map (perceptual aliasing, a crowd at the closing point); `GUARD_SCENES` (`office_slip`, the
demo) is the office whose wheels slip now and then, where the judge decides whom to trust.
"""

from scanguard.sim.config import SENSOR_PRESETS, ScenarioConfig
from scanguard.sim.engine import (
    CLOSURE_TRAPS,
    GMAPPING_TRAPS,
    GUARD_SCENES,
    SCENARIOS,
    ScanSink,
    SimulationResult,
    apply_overrides,
    load_scenario,
    parse_overrides,
    plan_simulation,
    simulate,
    simulate_run,
)
from scanguard.sim.limits import RunPlan
from scanguard.sim.raycast import cast_rays, measure
from scanguard.sim.world import World
from scanguard.sim.worldgen import build_world

__all__ = [
    "CLOSURE_TRAPS",
    "GMAPPING_TRAPS",
    "GUARD_SCENES",
    "SCENARIOS",
    "SENSOR_PRESETS",
    "RunPlan",
    "ScanSink",
    "ScenarioConfig",
    "SimulationResult",
    "World",
    "apply_overrides",
    "build_world",
    "cast_rays",
    "load_scenario",
    "measure",
    "parse_overrides",
    "plan_simulation",
    "simulate",
    "simulate_run",
]
