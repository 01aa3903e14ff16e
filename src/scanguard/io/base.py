"""The `Reader` protocol and helpers shared by the readers (pose alignment, summaries)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import InputError
from scanguard.geometry import interpolate_poses
from scanguard.scan import ScanSequence

log = logging.getLogger(__name__)

__all__ = ["Reader", "align_poses", "summarize"]


@runtime_checkable
class Reader(Protocol):
    """Something that turns a recording into a `ScanSequence`.

    Readers are small dataclasses: their fields are format-specific options (e.g.
    ``CarmenReader.max_range``), so ``dataclasses.replace(reader, **options)`` configures one.

    Attributes:
        name: Format name accepted by ``read_sequence(format=...)`` (e.g. ``"rosbag"``).
        extensions: File extensions handled, lower case with the dot (``".bag"``,
            ``".log.gz"``); a ROS 2 bag *directory* has the extension ``""``.
    """

    name: str
    extensions: tuple[str, ...]

    def read(
        self,
        path: Path,
        *,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        reference_topic: str | None = None,
    ) -> ScanSequence:
        """Read the recording at ``path`` (topics mean message types for text logs)."""
        ...


def align_poses(
    path: Path,
    what: str,
    stamps: NDArray[np.float64],
    poses: NDArray[np.float64],
    query: NDArray[np.float64],
    *,
    max_gap: float = 1.0,
) -> NDArray[np.float64]:
    """Interpolate timestamped poses to scan stamps, refusing a stream that misses the scans.

    Queries outside the pose stream are clamped to its ends (``geometry.interpolate_poses``);
    a warning names how many scans that affects when they are more than ``max_gap`` s out.

    Args:
        path: Recording (for messages).
        what: Name of the pose stream (topic, file) for messages.
        stamps: Pose times ``(M,)``.
        poses: Poses ``(M, 3)``.
        query: Scan times ``(N,)``.
        max_gap: Tolerated clamping distance (s) before warning.

    Returns:
        Poses ``(N, 3)`` at ``query``.

    Raises:
        InputError: No poses, or the pose stream and the scans do not overlap in time.
    """
    if stamps.size == 0:
        raise InputError(path, "no poses to align with the scans", location=what)
    t0, t1 = float(stamps.min()), float(stamps.max())
    if query.size and (query.max() < t0 - max_gap or query.min() > t1 + max_gap):
        raise InputError(
            path,
            f"poses cover {t0:.3f}..{t1:.3f} s but the scans cover "
            f"{query.min():.3f}..{query.max():.3f} s: no overlap",
            location=what,
        )
    outside = int(((query < t0 - max_gap) | (query > t1 + max_gap)).sum())
    if outside:
        log.warning(
            "%s: %s: %d scans lie more than %.1f s outside the poses; their poses are clamped",
            path,
            what,
            outside,
            max_gap,
        )
    return interpolate_poses(stamps, poses, query)


def summarize(seq: ScanSequence) -> dict[str, Any]:
    """Plain figures about a sequence, as printed by ``scanguard info``.

    Args:
        seq: The sequence.

    Returns:
        A dict with ``scans``, ``beams`` (sorted distinct counts), ``fov_deg``, ``range_min``,
        ``range_max``, ``rate_hz`` (None if unknown), ``duration_s``, ``invalid_fraction``,
        ``odometry``, ``reference``, ``reference_kind``, ``laser_offset``, ``topics`` and
        ``stamps_note`` (why rate/duration are unreliable, or None).
    """
    sensor = seq.sensor
    stamps_note = seq.metadata.get("stamps_unreliable")
    return {
        "name": seq.name,
        "scans": len(seq),
        "beams": sorted(set(seq.beam_counts.tolist())),
        "fov_deg": None if sensor is None else sensor.fov_deg,
        "range_min": None if sensor is None else sensor.range_min,
        "range_max": None if sensor is None else sensor.range_max,
        "rate_hz": None if stamps_note else seq.rate_hz,
        "duration_s": None if stamps_note else seq.duration,
        "invalid_fraction": seq.invalid_fraction,
        "odometry": seq.odometry is not None,
        "odometry_source": seq.metadata.get("odometry_source"),
        "reference": seq.reference is not None,
        "reference_kind": seq.reference_kind,
        "reference_source": seq.metadata.get("reference_source"),
        "laser_offset": seq.laser_offset.tolist(),
        "sensor": None if sensor is None else sensor.name,
        "format": seq.metadata.get("format"),
        "topics": dict(seq.metadata.get("topics", {})),
        "stamps_note": stamps_note,
    }
