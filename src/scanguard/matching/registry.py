"""`Matcher` protocol and the registry of named matchers (``"icp"``, ``"icp-paper"``, ...)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from numpy.typing import ArrayLike

from scanguard.errors import MatchingError
from scanguard.matching.config import ICPConfig
from scanguard.matching.correlative import CorrelativeMatcher
from scanguard.matching.icp import Method, PointsLike, match
from scanguard.matching.result import MatchResult


@runtime_checkable
class Matcher(Protocol):
    """Anything that aligns a current scan (source) to a previous scan (target)."""

    @property
    def name(self) -> str:
        """Registry name of the matcher."""
        ...

    def __call__(
        self, source: PointsLike, target: PointsLike, initial: ArrayLike | None = None
    ) -> MatchResult:
        """Match ``source`` to ``target`` from ``initial`` (None = identity)."""
        ...


@dataclass(frozen=True)
class ICPMatcher:
    """An ICP variant with a fixed config, usable as a `Matcher`.

    Attributes:
        name: Registry name.
        method: ``"point_to_point"`` or ``"point_to_line"``.
        config: The ICP settings.
    """

    name: str
    method: Method
    config: ICPConfig = field(default_factory=ICPConfig)

    def __call__(
        self, source: PointsLike, target: PointsLike, initial: ArrayLike | None = None
    ) -> MatchResult:
        """Match ``source`` to ``target`` (see `icp_point_to_point`)."""
        return match(self.method, source, target, initial, self.config)


MATCHERS: dict[str, Matcher] = {
    "icp": ICPMatcher("icp", "point_to_point", ICPConfig()),
    "icp-paper": ICPMatcher("icp-paper", "point_to_point", ICPConfig.paper()),
    "plicp": ICPMatcher("plicp", "point_to_line", ICPConfig()),
    "correlative": CorrelativeMatcher("correlative"),
}


def register_matcher(matcher: Matcher, *, replace: bool = False) -> None:
    """Add a matcher under ``matcher.name``.

    Raises:
        MatchingError: The name is taken and ``replace`` is False.
    """
    if matcher.name in MATCHERS and not replace:
        raise MatchingError(f"a matcher named {matcher.name!r} is already registered")
    MATCHERS[matcher.name] = matcher


def get_matcher(name: str, config: ICPConfig | None = None) -> Matcher:
    """The registered matcher ``name``, optionally an ICP one re-built with ``config``.

    Raises:
        MatchingError: Unknown name (the message lists the known ones), or a config given
            for a matcher that is not an ICP.
    """
    try:
        m = MATCHERS[name]
    except KeyError:
        known = ", ".join(sorted(MATCHERS))
        raise MatchingError(f"unknown matcher {name!r} (known: {known})") from None
    if config is None:
        return m
    if not isinstance(m, ICPMatcher):
        raise MatchingError(f"matcher {name!r} does not take an ICPConfig")
    return ICPMatcher(m.name, m.method, config)
