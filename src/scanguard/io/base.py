"""The `Reader` protocol and helpers shared by the readers.

Pose alignment, summaries, and the guards every reader applies to hostile input: pose bounds
(`check_poses`), printable and length-limited echoes of unknown tokens (`printable`,
`describe_counts`) and warnings issued once per file (`warn_once`).
"""

from __future__ import annotations

import gzip
import logging
import math
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError
from scanguard.geometry import interpolate_poses, quaternion_to_yaw
from scanguard.safeload import check_input_file, check_input_path, load_yaml
from scanguard.scan import ScanSequence

log = logging.getLogger(__name__)

__all__ = [
    "LENIENT_HINT",
    "MAX_COORDINATE",
    "MAX_STAMP",
    "QUATERNION_TOLERANCE",
    "Reader",
    "align_poses",
    "bad_pose_rows",
    "bad_stamps",
    "beams_disagree",
    "check_recording_path",
    "describe_counts",
    "planar_yaw",
    "pose_problem",
    "printable",
    "read_file_bytes",
    "stamp_problem",
    "stamps_note",
    "summarize",
    "warn_once",
]

MAX_COORDINATE = 1e6
"""Largest ``|x|`` or ``|y|`` (m) a reader accepts in a pose or a relation: a thousand
kilometres. Larger values are garbage (or a unit error) and would overflow the map and metric
code later on, so they are refused with the file and line."""

MAX_STAMP = 1e12
"""Largest ``|stamp|`` (s) a text reader accepts: some thirty thousand years. Larger values
are garbage (or nanoseconds taken for seconds) and break time interpolation."""

QUATERNION_TOLERANCE = 1e-3
"""Largest ``| |q| - 1 |`` of a quaternion read as it is; a larger one is normalised with a
warning (a writer that scaled or rounded it), a zero or non-finite one is refused."""

LENIENT_HINT = " (a lenient read, --lenient, skips such lines)"
"""Appended to the message of a malformed line or message in a strict read."""

MAX_ECHO = 32
"""Longest token (characters) echoed back from a file in a message."""

MAX_NAMES = 10
"""Most distinct names listed in a "found ..." message."""

_WARNED: set[tuple[Any, ...]] = set()


def printable(token: str | bytes, limit: int = MAX_ECHO) -> str:
    """A token from a file, safe to echo: printable ASCII only, at most ``limit`` characters.

    Control characters (terminal escape sequences), non-ASCII and undecodable bytes become
    ``?``; a longer token is cut and ends with ``...``.

    Args:
        token: The raw token.
        limit: Longest result, ``...`` included.

    Returns:
        The sanitised token.
    """
    if isinstance(token, bytes):
        token = token.decode("latin-1")
    cut = token[: limit + 1]
    text = "".join(c if " " <= c <= "~" else "?" for c in cut)
    if len(token) > limit:
        text = text[: max(0, limit - 3)] + "..."
    return text


def describe_counts(counts: Mapping[str, int], limit: int = MAX_NAMES) -> str:
    """``"NAME (count), ..."`` for the most frequent names, sanitised and bounded.

    At most ``limit`` names are listed (each through `printable`); the rest are summed up as
    ``"and K more (L lines)"``, so a binary or random file never floods the terminal.

    Args:
        counts: Occurrences by raw name.
        limit: Most names listed.

    Returns:
        The description, or ``"nothing"`` when ``counts`` is empty.
    """
    if not counts:
        return "nothing"
    ranked = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
    shown = [f"{printable(k)} ({v})" for k, v in ranked[:limit]]
    rest = ranked[limit:]
    if rest:
        shown.append(f"and {len(rest)} more ({sum(v for _, v in rest)} lines)")
    return ", ".join(shown)


def read_file_bytes(
    path: Path, logger: logging.Logger, *, missing: str = "file not found"
) -> bytes:
    """The bytes of a text recording, gunzipped when it starts with the gzip magic.

    Compression is told by the magic bytes, not the name: a file named ``.gz`` that is not
    gzip-compressed is read as it is, with one warning.

    Args:
        path: The file.
        logger: The reader's logger (for the warning).
        missing: The error text when the file does not exist.

    Raises:
        InputError: The file does not exist or cannot be read.
        FormatError: The gzip stream is truncated or corrupt.
    """
    if not path.exists():
        raise InputError(path, missing)
    # a FIFO would block the read, a folder fail with a traceback later
    check_input_file(path, what=missing.removesuffix(" not found"))
    try:
        with path.open("rb") as fh:
            magic = fh.read(2)
        if magic == b"\x1f\x8b":
            with gzip.open(path, "rb") as gz:
                data = gz.read()
        else:
            data = path.read_bytes()
    except EOFError:
        raise FormatError(path, "truncated gzip file (compressed stream ends early)") from None
    except (gzip.BadGzipFile, zlib.error) as exc:
        raise FormatError(path, f"corrupt gzip file ({printable(str(exc), 80)})") from None
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    if magic != b"\x1f\x8b" and path.name.lower().endswith(".gz"):
        warn_once(
            logger, path, "named .gz but not gzip-compressed (no gzip magic); read as plain text"
        )
    return data


def beams_disagree(n: int, angle_min: float, angle_max: float, increment: float) -> str | None:
    """Why a scan's ``n`` ranges disagree with its angle fields (None: they agree).

    ``angle_min``, ``angle_max`` and ``increment`` imply ``(max - min) / increment + 1``
    beams. One beam more or less is accepted (drivers differ on whether ``angle_max`` is the
    last beam's angle or one increment past it); beyond that the field of view or the beam
    angles would be wrong, silently, for every point of the scan, and which of the two is
    right cannot be told.
    """
    lo, hi, inc = float(angle_min), float(angle_max), float(increment)
    if n == 0 or inc == 0.0 or not all(math.isfinite(v) for v in (lo, hi, inc)):
        return None  # nothing to compare (LaserScan refuses what it cannot use)
    implied = (hi - lo) / inc + 1.0
    if abs(implied - n) <= 1.0 + 1e-6:
        return None
    return (
        f"{n} ranges, but angle_min {lo:.6g} to angle_max {hi:.6g} rad at increment "
        f"{inc:.6g} make {implied:.6g} beams: the scan's angles are inconsistent"
    )


def check_recording_path(path: str | Path) -> Path:
    """``path`` if it can be a recording: a regular file or a folder, never opened blindly.

    A FIFO, device or socket is refused without being opened (opening a FIFO blocks). A ROS 2
    bag's ``metadata.yaml`` (beside a ``.mcap``/``.db3`` or in the bag folder) is read by the
    bounded loader first, so an alias bomb or a file nested 50k deep is a one-line error
    before the bag library parses it.

    Raises:
        InputError: Missing, or not a regular file or folder.
        FormatError: The bag's ``metadata.yaml`` is not bounded, valid YAML.
    """
    p = check_input_path(path, what="recording", folder=True, missing="file not found")
    meta = p / "metadata.yaml" if p.is_dir() else p.parent / "metadata.yaml"
    if meta.exists() and (p.is_dir() or p.suffix in (".mcap", ".db3")):
        check_input_file(meta, what="ROS 2 bag metadata", error=FormatError)
        data = load_yaml(meta, what="ROS 2 bag metadata")
        if not isinstance(data, dict):
            raise FormatError(meta, "not a ROS 2 bag metadata file (not a YAML mapping)")
    return p


def warn_once(logger: logging.Logger, path: Path, message: str) -> None:
    """Log ``"path: message"`` as a warning once per file (and version of it) per process.

    Commands that read a recording more than once (or several commands run in one process,
    as in the tests or a notebook) repeat no warning; a repeat goes to the debug log.

    Args:
        logger: The reader's logger.
        path: The file the warning is about.
        message: The warning (already formatted).
    """
    try:
        st = path.stat()
        ident: tuple[Any, ...] = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    except OSError:
        ident = (str(path),)
    key = (*ident, message)
    if key in _WARNED:
        logger.debug("%s: %s (repeated)", path, message)
        return
    _WARNED.add(key)
    logger.warning("%s: %s", path, message)


def bad_pose_rows(poses: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Rows of ``(N, 3)`` poses that are not finite or lie beyond `MAX_COORDINATE`.

    Args:
        poses: Poses ``(x, y, theta)``.

    Returns:
        ``(N,)`` mask of the unusable rows.
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(p).all(axis=1) | (np.abs(p[:, :2]) > MAX_COORDINATE).any(axis=1)
    return np.asarray(bad, dtype=np.bool_)


def bad_stamps(stamps: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Stamps that are not finite or lie beyond `MAX_STAMP` (mask of the same shape)."""
    t = np.asarray(stamps, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.asarray(~np.isfinite(t) | (np.abs(t) > MAX_STAMP), dtype=np.bool_)


def planar_yaw(
    quaternions: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Yaw of quaternions ``(N, 4)`` ``(x, y, z, w)``, normalised first (every reader's rule).

    A quaternion scaled by 3 reads as the yaw of its unit version, not as a distorted angle.
    Components are scaled by their largest magnitude before the norm, so 1e200 does not
    overflow.

    Args:
        quaternions: The quaternions.

    Returns:
        ``(yaw (N,), repaired (N,), unusable (N,))``: ``repaired`` marks quaternions whose norm
        was off by more than `QUATERNION_TOLERANCE` (the caller warns), ``unusable`` zero or
        non-finite ones (the caller refuses them; their yaw is 0).
    """
    q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        scale = np.abs(q).max(axis=1, keepdims=True)
        unusable = ~np.isfinite(q).all(axis=1) | (scale[:, 0] < 1e-12)
        unit = np.where(unusable[:, None], np.array([0.0, 0.0, 0.0, 1.0]), q / scale)
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        norm = np.linalg.norm(q, axis=1)
        repaired = ~unusable & ~(np.abs(norm - 1.0) <= QUATERNION_TOLERANCE)
    return np.asarray(quaternion_to_yaw(unit), dtype=np.float64), repaired, unusable


def stamps_note(stamps: NDArray[np.float64], what: str) -> str | None:
    """Why stamps cannot time a recording, or None: fewer distinct values than half the scans.

    Rounded stamps (a CARMEN log's seconds) or stamps a driver never filled in (every header
    of a bag equal) give no rate, no duration and no alignment with poses.

    Args:
        stamps: The scan stamps.
        what: What the stamps are, e.g. ``"header stamp(s) on /scan"``.

    Returns:
        E.g. ``"only 1 distinct header stamp(s) on /scan for 30 scans"``, or None.
    """
    n = int(np.asarray(stamps).size)
    distinct = int(np.unique(stamps).size)
    if n < 2 or distinct >= 0.5 * n:
        return None
    return f"only {distinct} distinct {what} for {n} scans"


def stamp_problem(stamp: float) -> str:
    """One-line description of why a stamp is unusable (see `bad_stamps`)."""
    if not np.isfinite(stamp):
        return f"non-finite timestamp ({stamp})"
    return f"timestamp {stamp:.6g} s beyond +-{MAX_STAMP:.0e} s (nanoseconds?)"


def pose_problem(pose: NDArray[np.float64], what: str = "pose") -> str:
    """One-line description of why a pose row is unusable (see `bad_pose_rows`).

    Args:
        pose: The pose ``(x, y, theta)``.
        what: Its name in the message.

    Returns:
        E.g. ``"non-finite pose (x=nan)"`` or ``"pose x=1e+300 beyond 1e+06 m"``.
    """
    names = ("x", "y", "theta")
    for name, v in zip(names, pose, strict=True):
        if not np.isfinite(v):
            return f"non-finite {what} ({name}={v})"
    for name, v in zip(names[:2], pose[:2], strict=True):
        if abs(v) > MAX_COORDINATE:
            return f"{what} {name}={v:.6g} m beyond +-{MAX_COORDINATE:.0e} m"
    return f"unusable {what}"  # pragma: no cover - only called for bad rows


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
        ``range_max``, ``rate_hz`` (None if unknown), ``duration_s`` (span of the stamps,
        never negative), ``stamps_steps_back`` (consecutive stamps that go back),
        ``invalid_fraction``, ``odometry``, ``odometry_source``, ``odometry_note`` (how to get
        odometry the reader did not use by default, e.g. a CARMEN log's ODOM lines, or None),
        ``reference``, ``reference_kind``, ``laser_offset``, ``topics`` (message types the
        reader understands), ``other_lines`` (other line types of a text log, at most
        `MAX_NAMES` sanitised names, by count), ``skipped`` (malformed lines or messages
        skipped by a lenient read) and ``stamps_note`` (why rate/duration are unreliable, or
        None).
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
        # the span of the stamps: never negative, even when they run backwards
        "duration_s": None if stamps_note else seq.duration,
        "stamps_steps_back": seq.steps_back,
        "invalid_fraction": seq.invalid_fraction,
        "odometry": seq.odometry is not None,
        "odometry_source": seq.metadata.get("odometry_source"),
        "odometry_note": seq.metadata.get("odometry_hint"),
        "reference": seq.reference is not None,
        "reference_kind": seq.reference_kind,
        "reference_source": seq.metadata.get("reference_source"),
        "laser_offset": seq.laser_offset.tolist(),
        "sensor": None if sensor is None else sensor.name,
        "format": seq.metadata.get("format"),
        "topics": dict(seq.metadata.get("topics", {})),
        "other_lines": dict(seq.metadata.get("other_lines", {})),
        "skipped": int(seq.metadata.get("skipped_lines", 0)),
        "stamps_note": stamps_note,
    }
