"""``scanguard demo``: its simulated scene (an office whose wheels slip) and its settings."""

from __future__ import annotations

from scanguard.scan import ScanSequence

#: Simulated scene of ``scanguard demo`` (a built-in `scanguard.sim` scenario name): the office
#: of Environment 5 whose wheels slip now and then, where the judge decides whom to trust.
DEMO_SCENARIO = "office_slip"
#: Simulated seconds of ``scanguard demo`` (``--fast`` / CI: `DEMO_FAST_DURATION`): long enough
#: for two or three slip events.
DEMO_DURATION = 60.0
#: Simulated seconds of ``scanguard demo --fast``.
DEMO_FAST_DURATION = 3.0
#: GMapping's ``lskip`` in the demo: its PR2-like laser has 1040 beams, and matching every
#: third beam (347, a SICK's density) is what a ROS user sets for such a scanner; maps use
#: every beam.
DEMO_GMAPPING_LSKIP = 2


def demo_sequence(*, fast: bool = False, seed: int = 7) -> ScanSequence:
    """The demo's simulated scene (`DEMO_SCENARIO`).

    Args:
        fast: `DEMO_FAST_DURATION` instead of `DEMO_DURATION` simulated seconds (for CI).
        seed: Simulation seed.
    """
    from scanguard.sim import simulate

    return simulate(
        DEMO_SCENARIO, seed=seed, duration=DEMO_FAST_DURATION if fast else DEMO_DURATION
    )
