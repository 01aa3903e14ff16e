"""Scan matching: the paper's ICP, a point-to-line ICP, correlative matching, a registry.

See ``docs/matching.md`` for the algorithms, the stop rules and the speed figures.
"""

from scanguard.matching.config import CorrelativeConfig, ICPConfig
from scanguard.matching.correlative import (
    CorrelativeMatcher,
    CorrelativeResult,
    correlative_match,
    match_to_map,
)
from scanguard.matching.icp import as_points, icp_point_to_line, icp_point_to_point
from scanguard.matching.likelihood import LikelihoodGrid
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
    "CorrelativeConfig",
    "CorrelativeMatcher",
    "CorrelativeResult",
    "ICPConfig",
    "ICPMatcher",
    "LikelihoodGrid",
    "MatchResult",
    "Matcher",
    "as_points",
    "correlative_match",
    "get_matcher",
    "icp_point_to_line",
    "icp_point_to_point",
    "match_to_map",
    "register_matcher",
]
