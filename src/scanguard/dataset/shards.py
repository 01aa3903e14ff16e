"""One shard of a pair store: the self-describing HDF5 file of one sequence.

File layout (``format = "scanguard-pairs"``, ``format_version = 1``)::

    /                      attrs: environment, sequence, split, reference_kind, initial_guess,
                                  matcher, meta_json (matcher/label config, provenance), ...
    /scans/ranges          (N, B) float32, NaN-padded when beam counts differ
    /scans/n_beams         (N,) int32
    /scans/angle_min       (N,) float64
    /scans/angle_increment (N,) float64
    /scans/range_min       (N,) float32
    /scans/range_max       (N,) float32
    /scans/stamps          (N,) float64
    /scans/reference       (N, 3) float64   (robot poses; laser_offset in the root attrs)
    /scans/odometry        (N, 3) float64   (only when the recording has odometry)
    /pairs/<column>        (P, ...) one dataset per per-pair column, attrs["description"]
    /pairs/metrics/<name>  (P,) float64    match quality metrics (+ gmapping_score)

`write_sequence_file` writes a shard atomically, `read_sequence_file` reads one back, and
`inspect_shard` tells a build whether an existing shard is usable (and what it holds) or
corrupt. A store (`scanguard.dataset.store`) is a list of shards.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from scanguard.errors import FormatError, InputError, OutputError
from scanguard.fsutil import atomic_path, check_file_name
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL
from scanguard.safeload import loads_json
from scanguard.scan import LaserScan

log = logging.getLogger(__name__)

FORMAT = "scanguard-pairs"


FORMAT_VERSION = 1


SEQUENCE_DIR = "sequences"


#: Per-pair columns every file has, with their descriptions (stored as HDF5 attributes).
PAIR_COLUMNS: dict[str, str] = {
    "prev": "index of the previous scan (ICP target) in /scans",
    "curr": "index of the current scan (ICP source) in /scans",
    "estimate": "match estimate (x, y, theta): pose of the current sensor frame in the previous",
    "initial": "initial guess given to the matcher (x, y, theta), same convention",
    "reference": "reference relative pose of the sensor frames (x, y, theta)",
    "trans_error": "|xy| of inverse(reference) + estimate (m)",
    "rot_error": "|theta| of inverse(reference) + estimate (rad)",
    "disp_error": "mean displacement of the current scan's points under the error transform (m)",
    "label": "0 normal, 1 fault, -1 ambiguous (thresholds in the labels attrs of the root)",
}


@dataclass
class SequenceRecords:
    """Everything stored for one sequence (the in-memory form of one HDF5 file).

    Attributes:
        environment: Environment name (e.g. ``"lobby"`` or a recording's name).
        sequence: Sequence id, unique within a store (e.g. ``"lobby_03"``).
        split: ``"train"``, ``"val"``, ``"test"`` or ``"heldout"``.
        ranges: ``(N, B)`` float32 ranges, NaN-padded.
        n_beams: ``(N,)`` beams per scan.
        angle_min: ``(N,)`` first beam angle per scan.
        angle_increment: ``(N,)`` beam spacing per scan.
        range_min: ``(N,)`` valid range lower limit per scan.
        range_max: ``(N,)`` valid range upper limit per scan.
        stamps: ``(N,)`` scan stamps.
        reference: ``(N, 3)`` reference robot poses.
        odometry: ``(N, 3)`` odometry poses or None.
        laser_offset: Pose of the laser in the robot frame.
        pairs: Per-pair columns (see `PAIR_COLUMNS`).
        metrics: Per-pair quality metrics, one float64 column each.
        attrs: Scalar metadata (strings/numbers) for the root attributes.
        meta: Nested metadata (stored as JSON in ``meta_json``).
    """

    environment: str
    sequence: str
    split: str
    ranges: NDArray[np.float32]
    n_beams: NDArray[np.int32]
    angle_min: NDArray[np.float64]
    angle_increment: NDArray[np.float64]
    range_min: NDArray[np.float32]
    range_max: NDArray[np.float32]
    stamps: NDArray[np.float64]
    reference: NDArray[np.float64]
    odometry: NDArray[np.float64] | None
    laser_offset: NDArray[np.float64]
    pairs: dict[str, NDArray[Any]]
    metrics: dict[str, NDArray[np.float64]]
    attrs: dict[str, str | int | float] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def n_pairs(self) -> int:
        """Number of pairs."""
        return int(self.pairs["label"].shape[0])

    def counts(self) -> dict[str, int]:
        """Pairs per label name."""
        lab = self.pairs["label"]
        return {
            "normal": int((lab == NORMAL).sum()),
            "fault": int((lab == FAULT).sum()),
            "ambiguous": int((lab == AMBIGUOUS).sum()),
        }


def shard_meta(f: h5py.File, path: Path) -> dict[str, Any]:
    """A shard's ``meta_json`` attribute, decoded by the bounded loader (``{}`` if absent).

    Raises:
        FormatError: Not JSON, nested too deep, or not an object; names the file.
    """
    meta = loads_json(str(f.attrs.get("meta_json", "{}")), str(path), error=FormatError)
    if not isinstance(meta, dict):
        raise FormatError(path, "meta_json is not a JSON object")
    return meta


def sequence_file(sequence: str) -> str:
    """The path, relative to a dataset folder, of the shard of ``sequence``.

    Raises:
        OutputError: ``sequence`` cannot be a file name (``../../x``, a separator...).
    """
    try:
        check_file_name(sequence, "sequence name")
    except ValueError as exc:
        raise OutputError(f"{SEQUENCE_DIR}/", str(exc)) from None
    return f"{SEQUENCE_DIR}/{sequence}.h5"


def scans_to_arrays(scans: Sequence[LaserScan]) -> dict[str, NDArray[Any]]:
    """Pack scans (possibly with different beam counts) into NaN-padded arrays."""
    n = len(scans)
    width = max(s.n_beams for s in scans) if n else 0
    ranges = np.full((n, width), np.nan, dtype=np.float32)
    for i, s in enumerate(scans):
        ranges[i, : s.n_beams] = s.ranges
    return {
        "ranges": ranges,
        "n_beams": np.array([s.n_beams for s in scans], dtype=np.int32),
        "angle_min": np.array([s.angle_min for s in scans], dtype=np.float64),
        "angle_increment": np.array([s.angle_increment for s in scans], dtype=np.float64),
        "range_min": np.array([s.range_min for s in scans], dtype=np.float32),
        "range_max": np.array([s.range_max for s in scans], dtype=np.float32),
        "stamps": np.array([s.stamp for s in scans], dtype=np.float64),
    }


_SCAN_FIELDS = ("n_beams", "angle_min", "angle_increment", "range_min", "range_max", "stamps")


def write_sequence_file(path: str | Path, rec: SequenceRecords) -> Path:
    """Write one sequence to an HDF5 file atomically (temp file, then rename).

    Args:
        path: Destination ``.h5`` file.
        rec: The sequence's scans and pair records.

    Returns:
        The destination path.
    """
    dest = Path(path)
    with atomic_path(dest) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["environment"] = rec.environment
        f.attrs["sequence"] = rec.sequence
        f.attrs["split"] = rec.split
        f.attrs["laser_offset"] = np.asarray(rec.laser_offset, dtype=np.float64)
        for k, v in rec.attrs.items():
            f.attrs[k] = v
        f.attrs["meta_json"] = json.dumps(rec.meta, sort_keys=True)
        g = f.create_group("scans")
        chunk_rows = max(1, min(64, rec.ranges.shape[0]))
        g.create_dataset(
            "ranges",
            data=rec.ranges,
            compression="gzip",
            compression_opts=4,
            shuffle=True,
            chunks=(chunk_rows, max(1, rec.ranges.shape[1])) if rec.ranges.size else None,
        )
        for name in _SCAN_FIELDS:
            g.create_dataset(name, data=getattr(rec, name))
        g.create_dataset("reference", data=rec.reference)
        if rec.odometry is not None:
            g.create_dataset("odometry", data=rec.odometry)
        p = f.create_group("pairs")
        for name, arr in rec.pairs.items():
            ds = p.create_dataset(name, data=arr)
            if name in PAIR_COLUMNS:
                ds.attrs["description"] = PAIR_COLUMNS[name]
        m = p.create_group("metrics")
        for name, arr in rec.metrics.items():
            m.create_dataset(name, data=np.asarray(arr, dtype=np.float64))
    return dest


def check_format(f: h5py.File, path: Path) -> None:
    """Refuse a file that is not a scanguard pair file of this format version.

    Raises:
        InputError: Another format or format version.
    """
    if f.attrs.get("format") != FORMAT:
        raise InputError(path, f"not a scanguard pair file (format attr {f.attrs.get('format')!r})")
    ver = int(f.attrs.get("format_version", -1))
    if ver != FORMAT_VERSION:
        raise InputError(path, f"unsupported pair-file version {ver} (expected {FORMAT_VERSION})")


def read_sequence_file(path: str | Path) -> SequenceRecords:
    """Read one sequence file completely.

    Raises:
        InputError: The file is missing, not HDF5, or not a scanguard pair file.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "pair file not found")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise InputError(p, f"cannot open as HDF5 ({exc})") from None
    with f:
        check_format(f, p)
        g, pg = f["scans"], f["pairs"]
        attrs = {
            k: (v.item() if isinstance(v, np.generic) else v)
            for k, v in f.attrs.items()
            if k
            not in ("format", "format_version", "environment", "sequence", "split", "meta_json")
            and k != "laser_offset"
        }
        return SequenceRecords(
            environment=str(f.attrs["environment"]),
            sequence=str(f.attrs["sequence"]),
            split=str(f.attrs["split"]),
            ranges=g["ranges"][()],
            n_beams=g["n_beams"][()],
            angle_min=g["angle_min"][()],
            angle_increment=g["angle_increment"][()],
            range_min=g["range_min"][()],
            range_max=g["range_max"][()],
            stamps=g["stamps"][()],
            reference=g["reference"][()],
            odometry=g["odometry"][()] if "odometry" in g else None,
            laser_offset=np.asarray(f.attrs["laser_offset"], dtype=np.float64),
            pairs={k: pg[k][()] for k in pg if isinstance(pg[k], h5py.Dataset)},
            metrics={k: pg["metrics"][k][()] for k in pg["metrics"]},
            attrs=attrs,
            meta=shard_meta(f, p),
        )


@dataclass
class ShardState:
    """What an existing pair file holds (`inspect_shard`)."""

    ok: bool
    fingerprint: str | None = None
    entry: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    problem: str = ""


def inspect_shard(path: Path, file: str) -> ShardState:
    """Open an existing pair file: its fingerprint and manifest entry, or why it is corrupt."""
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if fmt != FORMAT:
                return ShardState(False, problem=f"not a scanguard pair file (format {fmt!r})")
            lab = np.asarray(f["pairs/label"][()])
            if lab.ndim != 1 or f["pairs/curr"].shape[0] != lab.size or "ranges" not in f["scans"]:
                return ShardState(False, problem="inconsistent pair columns")
            entry = {
                "file": file,
                "environment": str(f.attrs["environment"]),
                "sequence": str(f.attrs["sequence"]),
                "split": str(f.attrs["split"]),
                "pairs": int(lab.size),
                "normal": int((lab == NORMAL).sum()),
                "fault": int((lab == FAULT).sum()),
                "ambiguous": int((lab == AMBIGUOUS).sum()),
            }
            meta = shard_meta(f, path)
            fp = f.attrs.get("config_fingerprint")
            return ShardState(
                True,
                fingerprint=None if fp is None else str(fp),
                entry=entry,
                meta=meta if isinstance(meta, dict) else {},
            )
    except (OSError, KeyError, ValueError, TypeError, AttributeError, FormatError) as exc:
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return ShardState(False, problem=f"unreadable: {detail}")


def warn_corrupt(path: Path, state: ShardState) -> None:
    """Report a corrupt shard that the build is about to replace."""
    log.warning("%s: CORRUPT pair file (%s); rebuilding it", path, state.problem)


def shard_entry(rec: SequenceRecords, file: str) -> dict[str, Any]:
    """The manifest entry of a shard just written from ``rec`` at ``file`` (relative)."""
    return {
        "file": file,
        "environment": rec.environment,
        "sequence": rec.sequence,
        "split": rec.split,
        "pairs": rec.n_pairs,
        **rec.counts(),
    }
