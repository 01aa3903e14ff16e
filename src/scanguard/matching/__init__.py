"""Scan matching: the paper's point-to-point ICP, a point-to-line ICP, a matcher registry.

See ``docs/matching.md`` for the algorithms, the stop rules and the speed figures.
"""

from scanguard.matching.config import ICPConfig
from scanguard.matching.icp import as_points, icp_point_to_line, icp_point_to_point
from scanguard.matching.registry import (
    MATCHERS,
    ICPMatcher,
    Matcher,
    get_matcher,
    register_matcher,
)
from scanguard.matching.result import MatchResult

__all__ = [
    "MATCHERS",
    "ICPConfig",
    "ICPMatcher",
    "MatchResult",
    "Matcher",
    "as_points",
    "get_matcher",
    "icp_point_to_line",
    "icp_point_to_point",
    "register_matcher",
]
