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
from scanguard.io.rosbag import INFO_TOPIC
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


def check_bag_output(path: str | Path, *, overwrite: bool = False) -> Path:
    """Check a bag destination before simulating; return the path to write to.

    An existing bag there is replaced (when the new one is complete) only if scanguard wrote
    it (it has the ``/scanguard/info`` topic) or ``overwrite`` is given; a bag folder that
    holds any file that is not part of the bag (notes, a script) is never replaced, since
    the whole folder is.

    Args:
        path: ``*.mcap`` (one MCAP file) or a name without an extension (a ROS 2 bag
            folder); a symbolic link is followed.
        overwrite: Replace an existing bag that scanguard did not write.

    Returns:
        The resolved destination (links followed, absolute).

    Raises:
        OutputError: Another extension, a special file, a file where a folder is expected
            or the reverse, an existing folder that is not a ROS 2 bag or holds other
            files, an existing recording scanguard did not write (without ``overwrite``),
            or no permission to write there.
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
        real = check_output_path(given, "file", suffixes=(BAG_SUFFIX,))
        if real.is_file() and not overwrite and not _written_by_us(real):
            raise OutputError(given, _NOT_OURS)
        return real
    real = check_output_path(given, "dir", suffixes=("",))
    if not real.is_dir() or not any(real.iterdir()):
        return real
    meta = real / "metadata.yaml"
    if not meta.is_file():
        raise OutputError(given, "exists and is not a ROS 2 bag folder; not replacing it")
    foreign = sorted(
        p.name for p in real.iterdir() if p.name != meta.name and p.suffix not in _BAG_FILES
    )
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise OutputError(
            given,
            f"holds files that are not part of the bag ({shown}), and the whole folder would be "
            "replaced: not replacing it; write the bag elsewhere",
        )
    if not overwrite and not _written_by_us(meta):
        raise OutputError(given, _NOT_OURS)
    return real


_BAG_FILES = (BAG_SUFFIX, ".db3", ".db3-shm", ".db3-wal")
_NOT_OURS = (
    "a recording scanguard did not write is already there; not replacing it (choose another "
    "name, or pass --overwrite to replace it)"
)
#: How far into a bag file its channel list is looked for (MCAP writes the channels first).
_HEAD_BYTES = 4 * 1024 * 1024


def _written_by_us(path: Path) -> bool:
    """Whether the MCAP file or ``metadata.yaml`` at ``path`` has scanguard's info topic."""
    try:
        with path.open("rb") as fh:
            return INFO_TOPIC.encode() in fh.read(_HEAD_BYTES)
    except OSError:
        return False


def check_preview_output(path: str | Path, *, overwrite: bool = False) -> Path:
    """Check a preview destination (a ``.png`` file) before simulating.

    Args:
        path: The ``.png`` file.
        overwrite: Replace an existing file there (else it is refused: a picture of the
            user's is never lost).

    Raises:
        OutputError: Another extension, a special file or folder there, an existing file
            (without ``overwrite``), or not writable.
    """
    return check_output_path(
        path,
        "file",
        suffixes=(PREVIEW_SUFFIX,),
        refuse_existing=None if overwrite else "--overwrite",
    )


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
