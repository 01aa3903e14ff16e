"""Outputs of a simulation: destination checks before simulating, and a streaming bag writer.

`check_bag_output` accepts what ``scanguard simulate -o`` documents, a ``*.mcap`` file or a
ROS 2 bag folder (a name without an extension), and rejects anything else (``out.txt``, a
device, a FIFO, a folder that is not a bag, an unwritable place) before any simulation runs.

`BagStreamWriter` (the bag writer of `scanguard.io.rosbag_writer`, which `write_sequence` uses
too) writes the scans to the bag while they are simulated (a `ScanSink` for `simulate_run`), so a
run of any length needs constant memory, under a temporary name in the destination's folder,
renamed into place only when the run completed: a failed or interrupted run leaves no
half-written bag, and temporaries left by a killed process are removed by the next write to
the same place.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from scanguard.errors import OutputError
from scanguard.fsutil import check_output_path
from scanguard.io.rosbag_writer import BagWriter
from scanguard.scan import ScanSequence
from scanguard.sim.limits import format_bytes

log = logging.getLogger(__name__)

__all__ = [
    "BAG_SUFFIX",
    "PREVIEW_SUFFIX",
    "BagStreamWriter",
    "check_bag_output",
    "check_free_space",
    "check_preview_output",
]

#: Extension of a standalone MCAP bag file (any other output is a bag folder without one).
BAG_SUFFIX = ".mcap"
#: Extension of the preview image.
PREVIEW_SUFFIX = ".png"


def check_bag_output(path: str | Path) -> Path:
    """Check a bag destination before simulating; return the path to write to.

    Args:
        path: ``*.mcap`` (one MCAP file) or a name without an extension (a ROS 2 bag
            folder). An existing MCAP file or bag folder there is replaced when the new one
            is complete; a symbolic link is followed.

    Returns:
        The resolved destination (links followed, absolute).

    Raises:
        OutputError: Another extension, a special file, a file where a folder is expected
            or the reverse, an existing folder that is not a ROS 2 bag, or no permission to
            write there.
    """
    given = Path(path)
    if given.name in ("", ".", ".."):
        raise OutputError(given, "give the bag a name: NAME.mcap or a new folder NAME")
    suffix = given.suffix.lower()
    if suffix not in (BAG_SUFFIX, ""):
        raise OutputError(
            given,
            f"unsupported extension {given.suffix!r}: write a {BAG_SUFFIX} file or a ROS 2 bag "
            "folder (a name without an extension)",
        )
    if suffix == BAG_SUFFIX:
        return check_output_path(given, "file", suffixes=(BAG_SUFFIX,))
    real = check_output_path(given, "dir", suffixes=("",))
    if real.is_dir() and any(real.iterdir()) and not (real / "metadata.yaml").is_file():
        raise OutputError(given, "exists and is not a ROS 2 bag folder; not replacing it")
    return real


def check_preview_output(path: str | Path) -> Path:
    """Check a preview destination (a ``.png`` file) before simulating.

    Raises:
        OutputError: Another extension, a special file or folder there, or not writable.
    """
    return check_output_path(path, "file", suffixes=(PREVIEW_SUFFIX,))


def check_free_space(path: str | Path, need: float) -> None:
    """Check that the file system holding ``path`` has ``need`` bytes free.

    Raises:
        OutputError: Less space is free than needed.
    """
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        return  # cannot tell: the write itself reports a full disk
    if need > free:
        raise OutputError(
            path,
            f"the bag needs about {format_bytes(need)} but only {format_bytes(free)} are free "
            "there: lower --duration or write elsewhere",
        )


class BagStreamWriter(BagWriter):
    """The simulator's `ScanSink`: `scanguard.io.rosbag_writer.BagWriter` with both pose topics.

    Use it as a context manager around `simulate_run`: leaving the block normally moves the
    bag into place, leaving it with an exception (Ctrl-C included) removes everything it
    wrote. The temporary folder is made when the writer is created, so an unwritable
    destination fails before any simulation.

    Example:
        >>> with BagStreamWriter(check_bag_output("run.mcap")) as bag:  # doctest: +SKIP
        ...     simulate_run("lobby", seed=0, duration=60, sink=bag, keep_scans=False)
    """

    def begin(self, header: ScanSequence, *, odometry: bool = True, reference: bool = True) -> None:
        """Open the bag (a simulated run always has odometry and ground truth)."""
        super().begin(header, odometry=odometry, reference=reference)
