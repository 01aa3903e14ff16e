"""scanguard: CNN-based fault detection of 2D LiDAR scan matching in dynamic environments."""

from importlib.metadata import PackageNotFoundError, version

from scanguard.errors import ScanGuardError
from scanguard.scan import LaserScan, ScanSequence, SensorInfo

try:
    __version__ = version("scanguard")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0"

__all__ = ["LaserScan", "ScanGuardError", "ScanSequence", "SensorInfo", "__version__"]
