"""GMapping, the paper's SLAM back end: a Rao-Blackwellised particle filter (see `filter`).

Public face: `GMappingBackend` (a `scanguard.slam.backend.Backend`) and `GMappingConfig`
(ROS ``slam_gmapping`` parameter names and defaults).

`GMappingBackend` is imported when first asked for: every run reads `GMappingConfig` (the run
settings hold one), and the filter's compiled kernels cost a graph run ~0.25 s of start-up.
"""

from typing import TYPE_CHECKING, Any

from scanguard.slam.gmapping.config import GMappingConfig

if TYPE_CHECKING:
    from scanguard.slam.gmapping.filter import GMappingBackend


def __getattr__(name: str) -> Any:
    if name == "GMappingBackend":
        from scanguard.slam.gmapping.filter import GMappingBackend

        return GMappingBackend
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["GMappingBackend", "GMappingConfig"]
