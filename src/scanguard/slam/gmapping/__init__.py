"""GMapping, the paper's SLAM back end: a Rao-Blackwellised particle filter (see `filter`).

Public face: `GMappingBackend` (a `scanguard.slam.backend.Backend`) and `GMappingConfig`
(ROS ``slam_gmapping`` parameter names and defaults).
"""

from scanguard.slam.gmapping.config import GMappingConfig
from scanguard.slam.gmapping.filter import GMappingBackend

__all__ = ["GMappingBackend", "GMappingConfig"]
