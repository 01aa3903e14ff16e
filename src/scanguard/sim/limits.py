"""Run budget of a simulation: seed, duration, memory and work, checked before allocating.

Scenario fields are bounded one by one in `scanguard.sim.config`; what only their combination
decides (scans x beams, the people's tracks, the navigation grid) is estimated here and must
stay under `MEMORY_LIMIT_BYTES`, so that a mistyped ``--duration 1e9`` fails at once with a
one-line `ConfigError` naming the estimate and what to lower, instead of allocating hundreds
of GiB after minutes of work.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from scanguard.errors import ConfigError

if TYPE_CHECKING:
    from scanguard.sim.config import ScenarioConfig

#: Memory a simulation may need (scans kept in memory, tracks, people, navigation grid).
MEMORY_LIMIT_BYTES = 4 * 2**30
#: Most simulated scans of one run (10 M = 11.6 days at 10 Hz: many hours of computing).
MAX_SCANS = 10_000_000
#: Most physics sub-steps of one run (scans x sub-steps per scan).
MAX_PHYSICS_STEPS = 50_000_000
#: Most cells of the navigation grid (e.g. 500 m x 500 m at 0.1 m).
MAX_GRID_CELLS = 25_000_000
#: Largest seed (numpy seeds any non-negative integer; bags store it as an int64).
MAX_SEED = 2**63 - 1

#: Estimated bytes per scan kept in memory besides its ranges (object, stamp, two poses).
_SCAN_OVERHEAD = 1024
#: Estimated bytes per navigation grid cell at peak (occupancy, distance transform, labels).
GRID_BYTES_PER_CELL = 48
#: Estimated bytes per scan of a written bag besides the ranges (scan header, two Odometry
#: messages with their covariances, MCAP records).
_BAG_OVERHEAD = 1000


def format_bytes(n: float) -> str:
    """``n`` bytes in binary units (``"3.5 GiB"``)."""
    if not math.isfinite(n):
        return "an unbounded amount"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB" if n < 1000 else f"{n:.3g} PiB"


def check_seed(seed: Any) -> int:
    """The seed as an int.

    Raises:
        ConfigError: Not an integer, negative, or beyond `MAX_SEED`.
    """
    try:
        if isinstance(seed, bool):
            raise TypeError
        value = operator.index(seed)
    except TypeError:
        raise ConfigError(f"seed must be an integer >= 0, got {seed!r}") from None
    if value < 0:
        raise ConfigError(f"seed must be >= 0, got {value}")
    if value > MAX_SEED:
        raise ConfigError(f"seed must be <= {MAX_SEED}, got {value}")
    return value


def check_duration(duration: Any, name: str = "duration") -> float:
    """The duration (s) as a float.

    Raises:
        ConfigError: Not a number, not finite, or not > 0.
    """
    try:
        value = float(duration)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number of seconds, got {duration!r}") from None
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number of seconds, got {value}")
    if value <= 0:
        raise ConfigError(f"simulation {name} must be > 0 s, got {value}")
    return value


@dataclass(frozen=True)
class RunPlan:
    """Sizes of a simulation, known before it starts.

    Attributes:
        period: Seconds between simulated scans (before ``stride``).
        n_sub: Physics sub-steps per scan period.
        n_scans: Simulated scans (``floor(duration / period) + 1``).
        n_kept: Scans kept (every ``stride``-th, from the first).
        n_beams: Beams per scan.
        n_agents: People and carts.
        memory_bytes: Estimated memory of the run without the navigation grid.
    """

    period: float
    n_sub: int
    n_scans: int
    n_kept: int
    n_beams: int
    n_agents: int
    memory_bytes: float

    @property
    def bag_bytes(self) -> float:
        """Estimated size of the bag the run writes."""
        return self.n_kept * (4.0 * self.n_beams + _BAG_OVERHEAD)


def plan_run(
    cfg: ScenarioConfig, duration: float, *, keep_scans: bool = True, limit: float | None = None
) -> RunPlan:
    """Size a run and check it against the limits, before anything is allocated.

    Args:
        cfg: The resolved scenario.
        duration: Simulated seconds (already checked with `check_duration`).
        keep_scans: Whether the scans are kept in memory (False: streamed to a writer).
        limit: Memory limit (bytes); default `MEMORY_LIMIT_BYTES`.

    Returns:
        The plan.

    Raises:
        ConfigError: The run would need more memory than the limit, more than `MAX_SCANS`
            scans or more than `MAX_PHYSICS_STEPS` physics steps; the message gives the
            estimate and what to lower.
    """
    limit = MEMORY_LIMIT_BYTES if limit is None else limit
    info = cfg.sensor.info()
    period = cfg.scan_period()
    n_sub = max(1, math.ceil(period / cfg.physics_dt - 1e-9))
    n_float = duration / period  # period >= 0.01 s and duration finite: finite or +inf
    beams, agents = info.n_beams, cfg.people.count + cfg.people.carts
    kept_float = n_float / cfg.stride + 1
    per_scan = 24.0 + 17.0 * agents  # robot path, people's tracks and pause flags
    per_kept = (4.0 * beams + _SCAN_OVERHEAD) if keep_scans else 64.0
    memory = (n_float + 1) * per_scan + kept_float * per_kept + 80.0 * agents**2
    what = f"{cfg.name!r}: {duration:g} s at {1 / period:g} Hz"
    if not memory <= limit:
        lower = "the duration (--duration)"
        if keep_scans and kept_float * per_kept > (n_float + 1) * per_scan:
            lower += ", the scan rate or sensor.n_beams, or raise stride"
        elif agents:
            lower += " or people.count"
        raise ConfigError(
            f"{what} ({n_float + 1:.3g} scans of {beams} beams, {agents} agents) needs about "
            f"{format_bytes(memory)} of memory, more than the {format_bytes(limit)} limit: "
            f"lower {lower}"
        )
    if not n_float + 1 <= MAX_SCANS:
        raise ConfigError(
            f"{what} is {n_float + 1:.3g} scans, more than the limit of {MAX_SCANS:,}: lower "
            "the duration (--duration) or the scan rate"
        )
    if not (n_float + 1) * n_sub <= MAX_PHYSICS_STEPS:
        raise ConfigError(
            f"{what} with physics_dt {cfg.physics_dt:g} s is {(n_float + 1) * n_sub:.3g} physics "
            f"steps, more than the limit of {MAX_PHYSICS_STEPS:,}: lower the duration "
            "(--duration) or raise physics_dt"
        )
    n_scans = math.floor(n_float + 1e-9) + 1
    return RunPlan(
        period=period,
        n_sub=n_sub,
        n_scans=n_scans,
        n_kept=(n_scans - 1) // cfg.stride + 1,
        n_beams=beams,
        n_agents=agents,
        memory_bytes=memory,
    )


def check_grid(
    name: str, shape: tuple[int, int], resolution: float, *, other_bytes: float = 0.0
) -> None:
    """Check a navigation grid's size before it is allocated.

    Args:
        name: World name (for the message).
        shape: Grid rows and columns.
        resolution: Cell size (m).
        other_bytes: Memory the rest of the run needs (`RunPlan.memory_bytes`).

    Raises:
        ConfigError: More than `MAX_GRID_CELLS` cells, or the grid plus ``other_bytes`` over
            `MEMORY_LIMIT_BYTES`.
    """
    cells = float(shape[0]) * float(shape[1])
    need = cells * GRID_BYTES_PER_CELL
    size = f"{shape[1] * resolution:.0f} x {shape[0] * resolution:.0f} m"
    if cells > MAX_GRID_CELLS or need + other_bytes > MEMORY_LIMIT_BYTES:
        raise ConfigError(
            f"world {name!r}: the navigation grid of {size} at {resolution:g} m is "
            f"{cells:.3g} cells (about {format_bytes(need)}), more than the limit of "
            f"{MAX_GRID_CELLS:,} cells or {format_bytes(MEMORY_LIMIT_BYTES)} in all: make the "
            "world smaller (world.params) or raise world.grid_resolution"
        )
