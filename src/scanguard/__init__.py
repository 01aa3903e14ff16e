"""scanguard: CNN-based fault detection of 2D LiDAR scan matching in dynamic environments."""

from importlib.metadata import PackageNotFoundError, version

# first, before any module defines a numba kernel: numba's cache goes to the user's cache
# folder (NUMBA_CACHE_DIR when set), bounded in size
from scanguard.fsutil.numba_cache import setup_numba_cache

setup_numba_cache()

from scanguard.errors import ScanGuardError  # noqa: E402
from scanguard.scan import LaserScan, ScanSequence, SensorInfo  # noqa: E402

try:
    __version__ = version("scanguard")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0"

__all__ = ["LaserScan", "ScanGuardError", "ScanSequence", "SensorInfo", "__version__"]
