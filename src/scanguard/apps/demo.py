"""``scanguard demo``: the simulated crowded scene it runs, and its settings."""

from __future__ import annotations

from scanguard.scan import ScanSequence

#: Simulated scene of ``scanguard demo`` (a built-in `scanguard.sim` scenario name).
DEMO_SCENARIO = "lobby"
#: Simulated seconds of ``scanguard demo`` (``--fast`` / CI: `DEMO_FAST_DURATION`).
DEMO_DURATION = 30.0
#: Simulated seconds of ``scanguard demo --fast``.
DEMO_FAST_DURATION = 3.0
#: GMapping's ``lskip`` in the demo: its RPLidar has 1440 beams, and matching every 4th beam
#: (360, a SICK's density) is what a ROS user sets for such a scanner; maps use every beam.
DEMO_GMAPPING_LSKIP = 3


def demo_sequence(*, fast: bool = False, seed: int = 7) -> ScanSequence:
    """The demo's simulated crowded scene (`DEMO_SCENARIO`).

    Args:
        fast: `DEMO_FAST_DURATION` instead of `DEMO_DURATION` simulated seconds (for CI).
        seed: Simulation seed.
    """
    from scanguard.sim import simulate

    return simulate(
        DEMO_SCENARIO, seed=seed, duration=DEMO_FAST_DURATION if fast else DEMO_DURATION
    )
