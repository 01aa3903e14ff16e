"""Readers and writers: every recording becomes a `ScanSequence`.

``read_sequence`` picks a reader from the explicit ``READERS`` registry by file extension
(or by ``format=``), then optionally attaches reference poses from a TUM file or the
``"static"`` reference (the sensor never moved). ``write_sequence`` writes a ROS 2 bag with
MCAP storage (``*.mcap`` -> one standalone MCAP file, other paths -> a bag folder), which
``read_sequence`` opens by the same path.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from scanguard.errors import InputError, UnknownFormatError
from scanguard.io.base import Reader, align_poses, check_recording_path, summarize
from scanguard.io.carmen import CarmenReader
from scanguard.io.rosbag import RosbagReader
from scanguard.io.rosbag_writer import write_rosbag
from scanguard.io.tum import read_tum, write_tum
from scanguard.scan import ScanSequence

log = logging.getLogger(__name__)

__all__ = [
    "READERS",
    "Reader",
    "get_reader",
    "read_sequence",
    "read_tum",
    "summarize",
    "write_sequence",
    "write_tum",
]

_ROSBAG = RosbagReader()
_CARMEN = CarmenReader()

READERS: dict[str, Reader] = {ext: r for r in (_ROSBAG, _CARMEN) for ext in r.extensions}
"""Readers by lower-case file extension (``""`` = a ROS 2 bag folder)."""


def _extension(path: Path) -> str:
    if path.is_dir():
        return ""
    name = path.name.lower()
    # compound extensions first (".log.gz" must not be taken for an unknown ".gz")
    for ext in sorted((e for e in READERS if e), key=len, reverse=True):
        if name.endswith(ext):
            return ext
    return path.suffix.lower()


def get_reader(path: str | Path, format: str | None = None) -> Reader:
    """Reader for ``path``: by ``format`` (a reader name or an extension) or by extension.

    Raises:
        UnknownFormatError: Nothing is registered for the extension or format name.
    """
    p = Path(path)
    if format is not None:
        key = format.lower()
        for reader in READERS.values():
            if reader.name == key:
                return reader
        ext = key if key.startswith(".") else f".{key}"
        if ext in READERS:
            return READERS[ext]
        names = sorted({r.name for r in READERS.values()})
        raise UnknownFormatError(p, f"unknown format {format!r} (known: {', '.join(names)})")
    ext = _extension(p)
    if ext in READERS:
        return READERS[ext]
    known = ", ".join(sorted(e for e in READERS if e))
    raise UnknownFormatError(
        p,
        f"unknown file extension {ext or '(none)'!r}; known: {known}, ROS 2 bag folders "
        "(or pass --format)",
    )


def read_sequence(
    path: str | Path,
    *,
    format: str | None = None,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    reference_topic: str | None = None,
    reference: str | Path | None = None,
    reader_options: Mapping[str, Any] | None = None,
    lenient: bool = False,
    max_scans: int | None = None,
) -> ScanSequence:
    """Read any supported recording.

    Args:
        path: ROS 1 ``.bag``, ROS 2 bag folder / ``.db3`` / ``.mcap``, or a CARMEN log
            (``.log``, ``.clf``, optionally ``.gz``).
        format: Reader name (``"rosbag"``, ``"carmen"``) or extension; default: from
            ``path``.
        scan_topic: LaserScan topic (bags) or laser message type (CARMEN: ``FLASER``...).
        odom_topic: Odometry topic (CARMEN: ``"ODOM"`` or ``"laser"``).
        reference_topic: Reference pose topic (CARMEN: ``"laser"``).
        reference: A TUM trajectory file whose poses (interpolated to the scan stamps)
            replace the reference, or ``"static"`` (sensor never moved: zeros).
        reader_options: Format-specific reader fields, e.g. ``{"max_range": 50.0}`` or
            ``{"corrected": True}`` (a SLAM-corrected log whose name does not say so) for
            CARMEN.
        lenient: Skip malformed lines / messages (wrong count of values, garbled number,
            non-finite or absurd pose or stamp, invalid scan geometry) of the recording and
            of a TUM ``reference``, with one warning giving their count
            (``metadata["skipped_lines"]``), instead of refusing the file.
        max_scans: Read only the first scans (None: all): the reader stops there (the
            odometry and reference it needs to align them are read on), so a long recording
            costs neither the time nor the memory of a full read.

    Returns:
        The sequence.

    Raises:
        InputError: Missing file, unknown topic, bad reader option...
        UnknownFormatError: No reader for the extension / format.
        FormatError: Garbled or truncated contents, a malformed line (strict reading), not
            the format asked for.
    """
    p = check_recording_path(path)
    reader = get_reader(p, format)
    if reader_options:
        fields = {f.name for f in dataclasses.fields(reader)} - {"name", "extensions"}  # type: ignore[arg-type]
        unknown = sorted(set(reader_options) - fields)
        if unknown:
            raise InputError(
                p,
                f"unknown {reader.name} reader option(s) {', '.join(unknown)} "
                f"(known: {', '.join(sorted(fields)) or 'none'})",
            )
        reader = dataclasses.replace(reader, **reader_options)  # type: ignore[type-var]
    if lenient and getattr(reader, "lenient", None) is False:
        reader = dataclasses.replace(reader, lenient=True)  # type: ignore[type-var]
    if max_scans is not None:
        if max_scans < 1:
            raise InputError(p, f"max_scans must be at least 1, got {max_scans}")
        if hasattr(reader, "max_scans"):
            reader = dataclasses.replace(reader, max_scans=max_scans)  # type: ignore[type-var]
    seq = reader.read(
        p, scan_topic=scan_topic, odom_topic=odom_topic, reference_topic=reference_topic
    )
    if max_scans is not None and len(seq) > max_scans:  # a reader that cannot stop early
        seq = seq.subsequence(slice(0, max_scans))
    if reference is not None:
        attach_reference(seq, reference, lenient=lenient)
    return seq


def attach_reference(
    seq: ScanSequence, reference: str | Path, *, lenient: bool = False
) -> ScanSequence:
    """Set the reference poses of ``seq`` from a TUM file or ``"static"`` (in place).

    Args:
        seq: The sequence (modified and returned).
        reference: TUM trajectory path, or ``"static"`` for a sensor that never moved.
        lenient: Skip malformed lines of the TUM file (see `read_tum`).

    Raises:
        InputError: The TUM file is missing, garbled or does not overlap the scans in time,
            or the scans' stamps are unreliable (too few distinct values to align poses).
    """
    n = len(seq)
    if str(reference).lower() == "static":
        seq.reference = np.zeros((n, 3))
        seq.reference_kind = "static"
        seq.metadata["reference_source"] = "static"
        return seq
    tum = Path(reference)
    stamps, poses = read_tum(tum, lenient=lenient)
    note = seq.metadata.get("stamps_unreliable")
    if note:
        # every scan would get the pose at one stamp: labels from it would all be "normal"
        raise InputError(tum, f"cannot align TUM poses with the scans of {seq.name}: {note}")
    seq.reference = align_poses(tum, "TUM poses", stamps, poses, seq.stamps)
    seq.reference_kind = "tum"
    seq.metadata["reference_source"] = str(tum)
    return seq


def write_sequence(
    seq: ScanSequence,
    path: str | Path,
    *,
    scan_topic: str = "/scan",
    odom_topic: str = "/odom",
    reference_topic: str = "/ground_truth",
) -> Path:
    """Write ``seq`` as a ROS 2 bag with MCAP storage.

    A ``*.mcap`` path gives one standalone MCAP file there; any other path gives a bag folder.
    Both are written atomically and open again with `read_sequence` by the same path.

    Args:
        seq: The sequence.
        path: Destination.
        scan_topic: LaserScan topic.
        odom_topic: ``nav_msgs/Odometry`` topic for the odometry (if any).
        reference_topic: ``nav_msgs/Odometry`` topic for the reference poses (if any).

    Returns:
        The written path.
    """
    return write_rosbag(
        seq, path, scan_topic=scan_topic, odom_topic=odom_topic, reference_topic=reference_topic
    )
