"""A pair store: the labelled scan pairs of one or more builds, read as one (HDF5 shards).

A store is a list of shards, one self-describing HDF5 file per sequence (layout in
`scanguard.dataset.shards`). `PairStore.open` accepts a build directory (its
``manifest.json``), a single file, or any list of those, so several builds (simulation, real
recordings) can be used together without copying; `merge_stores` copies them into one
directory with one manifest.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from scanguard.dataset.shard_check import read_dataset, read_pair_table
from scanguard.dataset.shards import (
    FORMAT,
    FORMAT_VERSION,
    SEQUENCE_DIR,
    check_format,
    sequence_file,
    shard_meta,
)
from scanguard.errors import InputError, OutputError
from scanguard.fsutil import ResultDir, atomic_write_text
from scanguard.geometry import compose, relative, transform_points
from scanguard.pairs.labels import (
    AMBIGUOUS,
    FAULT,
    NORMAL,
    LabelConfig,
    assign_labels,
    non_finite_errors,
)
from scanguard.safeload import load_json
from scanguard.scan import LaserScan

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"


def read_manifest(directory: str | Path) -> dict[str, Any]:
    """Read and check a build directory's ``manifest.json``.

    Raises:
        InputError: No manifest, invalid JSON, or a manifest of the wrong shape (not an
            object, ``sequences`` not a list of entries with a relative ``file``, ...); the
            message names the manifest.
    """
    d = Path(directory)
    mp = d / MANIFEST
    if not mp.exists():
        raise InputError(d, f"no {MANIFEST}: not a scanguard dataset directory")
    # bounded: a FIFO, a binary file or JSON nested too deep is a one-line error
    data = load_json(mp, what="dataset manifest", error=InputError)
    if not isinstance(data, dict):
        raise InputError(mp, f"not a scanguard dataset manifest (a JSON {_json_type(data)})")
    if data.get("format") != FORMAT:
        raise InputError(mp, f"not a scanguard dataset manifest (format {data.get('format')!r})")
    check_manifest(data, mp)
    return data


def _json_type(value: Any) -> str:
    names = {dict: "object", list: "list", str: "string", bool: "boolean", type(None): "null"}
    return names.get(type(value), "number")


def check_manifest(data: dict[str, Any], source: str | Path) -> None:
    """Check the shape of a manifest's ``sequences``, ``complete`` and ``pending`` fields.

    Raises:
        InputError: A field has the wrong type, or an entry's ``file`` is not a relative
            path inside the build directory.
    """
    seqs = data.get("sequences")
    if not isinstance(seqs, list):
        raise InputError(source, f"'sequences' is a {_json_type(seqs)}, not a list")
    for i, entry in enumerate(seqs):
        if not isinstance(entry, dict):
            raise InputError(source, f"sequences[{i}] is a {_json_type(entry)}, not an object")
        file = entry.get("file")
        if not isinstance(file, str) or not file:
            raise InputError(source, f"sequences[{i}] has no 'file' string")
        rel = Path(file)
        if rel.is_absolute() or ".." in rel.parts:
            raise InputError(source, f"sequences[{i}]: file {file!r} is outside the directory")
        if not isinstance(entry.get("sequence", ""), str):
            raise InputError(source, f"sequences[{i}]: 'sequence' is not a string")
    if "complete" in data and not isinstance(data["complete"], bool):
        raise InputError(source, f"'complete' is a {_json_type(data['complete'])}, not a boolean")
    pending = data.get("pending", [])
    if not isinstance(pending, list) or not all(isinstance(x, dict) for x in pending):
        raise InputError(source, "'pending' is not a list of objects")


def manifest_incomplete(data: dict[str, Any]) -> str | None:
    """Why a manifest describes an unfinished build, or None when it is complete.

    A build is unfinished while its manifest says ``complete: false`` or lists ``pending``
    work (planned sequences or recordings not built yet, e.g. after Ctrl-C). Manifests
    without a ``complete`` field (merged stores, older builds) count as complete.
    """
    pending = data.get("pending") or []
    if data.get("complete", True) is not False and not pending:
        return None
    if not pending:
        return "marked incomplete"
    names = [
        str(x.get("sequence") or Path(str(x.get("recording") or x.get("source") or "?")).name)
        for x in pending
        if isinstance(x, dict)
    ]
    shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
    return f"{len(pending)} sequence(s) or recording(s) not built: {shown}"


def write_manifest(directory: str | Path, manifest: dict[str, Any]) -> Path:
    """Write ``manifest.json`` atomically (see `scanguard.dataset.manifest` for updates)."""
    mp = Path(directory) / MANIFEST
    atomic_write_text(mp, json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    return mp


def _odometry_increments(
    f: h5py.File, prev: NDArray[np.integer[Any]], curr: NDArray[np.integer[Any]], path: Path
) -> NDArray[np.float64]:
    """``(P, 3)`` odometry increments of a file's pairs in the sensor frame (NaN: none).

    Corrected CARMEN logs never expose odometry (their ODOM lines are not aligned with the
    scans); a file whose pairs were seeded with odometry simulated from the reference has no
    recorded odometry either, so it gets NaN rows, never the simulated steps (they are built
    from the answer).
    """
    out = np.full((len(prev), 3), np.nan)
    g = f["scans"]
    if "odometry" not in g or str(f.attrs.get("reference_kind", "")) == "corrected_log":
        return out
    odo = np.asarray(read_dataset(g, "odometry", path), dtype=np.float64)
    sensor = compose(odo, np.asarray(f.attrs["laser_offset"], dtype=np.float64))
    return np.asarray(relative(sensor[prev], sensor[curr]), dtype=np.float64)


def _expand_sources(
    sources: str | Path | Iterable[str | Path],
    incomplete: list[tuple[Path, str]] | None = None,
) -> list[Path]:
    if isinstance(sources, str | Path):
        sources = [sources]
    sources = list(sources)
    files: list[Path] = []
    for src in sources:
        p = Path(src)
        if p.is_dir():
            man = read_manifest(p)
            why = manifest_incomplete(man)
            if why is not None and incomplete is not None:
                incomplete.append((p, why))
            for entry in man["sequences"]:
                fp = p / entry["file"]
                if not fp.is_file():
                    raise InputError(fp, "listed in the manifest but missing")
                files.append(fp)
        elif p.is_file():
            files.append(p)
        else:
            raise InputError(p, "no such dataset file or directory")
    if not files:
        where = ", ".join(str(s) for s in sources) or "the given sources"
        raise InputError(None, f"no sequence files in {where}")
    return files


@dataclass
class _ScanCache:
    ranges: NDArray[np.float32]
    n_beams: NDArray[np.int32]
    angle_min: NDArray[np.float64]
    angle_increment: NDArray[np.float64]
    range_min: NDArray[np.float32]
    range_max: NDArray[np.float32]
    stamps: NDArray[np.float64]


_SCAN_CACHE_FIELDS = (
    "ranges",
    "n_beams",
    "angle_min",
    "angle_increment",
    "range_min",
    "range_max",
    "stamps",
)


class PairStore:
    """Read access to one or more pair files as a single table of pairs.

    ``records`` holds one numpy column per pair field, concatenated over files: the
    `PAIR_COLUMNS`, every metric (by its name), ``environment``, ``sequence``, ``split``
    (str arrays), ``file`` (index into `files`), ``pair`` (index within the file) and
    ``odometry_increment`` (``(P, 3)`` odometry increment of the pair in the sensor frame, the
    estimate's convention; NaN rows where the file has no usable odometry).
    Scans are loaded lazily per file and cached.
    """

    def __init__(self, files: Sequence[Path], incomplete: Sequence[tuple[Path, str]] = ()) -> None:
        self.files: list[Path] = list(files)
        #: Build directories of this store whose build is unfinished, with the reason
        #: (`manifest_incomplete`); `train` refuses such a store unless told otherwise.
        self.incomplete: list[tuple[Path, str]] = list(incomplete)
        self.file_attrs: list[dict[str, Any]] = []
        self.file_meta: list[dict[str, Any]] = []
        cols: dict[str, list[NDArray[Any]]] = {}
        metric_sets: list[set[str]] = []
        seen: dict[str, Path] = {}
        for fi, path in enumerate(self.files):
            try:
                f = h5py.File(path, "r")
            except OSError as exc:
                raise InputError(path, f"cannot open as HDF5 ({exc})") from None
            with f:
                check_format(f, path)
                table = read_pair_table(f, path)  # names, shapes, indices: checked once here
                seq = table.sequence
                if seq in seen:
                    raise InputError(path, f"sequence {seq!r} is also in {seen[seq]}")
                seen[seq] = path
                attrs = {k: f.attrs[k] for k in f.attrs if k != "meta_json"}
                self.file_attrs.append(attrs)
                self.file_meta.append(shard_meta(f, path))
                n = int(table.columns["label"].shape[0])
                for name, arr in table.columns.items():
                    cols.setdefault(name, []).append(arr)
                metric_sets.append(set(table.metrics))
                for name, arr in table.metrics.items():
                    cols.setdefault(name, []).append(arr)
                for name, value in (
                    ("environment", table.environment),
                    ("sequence", seq),
                    ("split", table.split),
                ):
                    cols.setdefault(name, []).append(np.full(n, value, dtype=object))
                cols.setdefault("odometry_increment", []).append(
                    _odometry_increments(f, table.columns["prev"], table.columns["curr"], path)
                )
                cols.setdefault("file", []).append(np.full(n, fi, dtype=np.int32))
                cols.setdefault("pair", []).append(np.arange(n, dtype=np.int32))
        # metrics differ between matchers: keep only those every file has
        common = set.intersection(*metric_sets) if metric_sets else set()
        self.metric_names: list[str] = sorted(common)
        all_metrics = set.union(*metric_sets) if metric_sets else set()
        self.records: dict[str, NDArray[Any]] = {}
        for name, parts in cols.items():
            if name in all_metrics and name not in common:
                log.warning("metric %r is not in every file of the store; dropped", name)
                continue
            if len(parts) != len(self.files):
                continue
            self.records[name] = np.concatenate(parts)
        self._warn_non_finite_labels()
        self._scans: dict[int, _ScanCache] = {}
        self._laser_offsets = [
            np.asarray(a["laser_offset"], dtype=np.float64) for a in self.file_attrs
        ]

    def _warn_non_finite_labels(self) -> None:
        """Warn about pairs labelled from non-finite errors (files built before the fix)."""
        r = self.records
        if not all(k in r for k in ("trans_error", "rot_error", "disp_error", "label")):
            return
        bad = non_finite_errors(r["trans_error"], r["rot_error"], r["disp_error"])
        bad &= r["label"] != AMBIGUOUS
        if bad.any():
            files = sorted({str(self.files[i]) for i in np.unique(r["file"][bad]).tolist()})
            log.warning(
                "%s: %d pair(s) carry a label computed from non-finite errors; rebuild with "
                "--overwrite (they are ambiguous now)",
                files[0] if len(files) == 1 else f"{files[0]} and {len(files) - 1} more",
                int(bad.sum()),
            )

    @classmethod
    def open(cls, sources: str | Path | Iterable[str | Path]) -> PairStore:
        """Open build directories and/or pair files as one store.

        A build directory whose build is unfinished (interrupted, ``complete: false``) opens
        with a warning and is listed in `incomplete`.

        Args:
            sources: A dataset directory (with ``manifest.json``), a ``.h5`` pair file, or a
                list mixing both.

        Raises:
            InputError: A source is missing or not a scanguard dataset.
        """
        incomplete: list[tuple[Path, str]] = []
        files = _expand_sources(sources, incomplete)
        for path, why in incomplete:
            log.warning(
                "%s: incomplete dataset build (%s); finish it by running the same "
                "`dataset build` command again",
                path,
                why,
            )
        return cls(files, incomplete)

    def __len__(self) -> int:
        return int(self.records["label"].shape[0])

    @property
    def labels(self) -> NDArray[np.int8]:
        """Label column (0 normal, 1 fault, -1 ambiguous)."""
        return self.records["label"]

    @property
    def environments(self) -> list[str]:
        """Environment names in store order (first appearance)."""
        return list(dict.fromkeys(self.records["environment"].tolist()))

    def indices(
        self,
        split: str | Sequence[str] | None = None,
        *,
        environment: str | Sequence[str] | None = None,
        include_ambiguous: bool = False,
    ) -> NDArray[np.int64]:
        """Pair indices filtered by split, environment and label.

        Args:
            split: One split name or several; None = all (including ``"heldout"``).
            environment: One environment or several; None = all.
            include_ambiguous: Keep ambiguous pairs (excluded by default: not trainable).

        Returns:
            Sorted int64 indices into `records`.
        """
        mask = np.ones(len(self), dtype=bool)
        if split is not None:
            names = [split] if isinstance(split, str) else list(split)
            mask &= np.isin(self.records["split"], names)
        if environment is not None:
            envs = [environment] if isinstance(environment, str) else list(environment)
            mask &= np.isin(self.records["environment"], envs)
        if not include_ambiguous:
            mask &= self.records["label"] != AMBIGUOUS
        return np.flatnonzero(mask).astype(np.int64)

    def relabel(self, config: LabelConfig) -> NDArray[np.int8]:
        """Labels recomputed from the stored errors with other thresholds."""
        r = self.records
        return assign_labels(r["trans_error"], r["rot_error"], r["disp_error"], config)

    def label_config(self, file: int = 0) -> LabelConfig:
        """The label thresholds a file was built with."""
        return LabelConfig.from_dict(self.file_meta[file]["labels"], source=str(self.files[file]))

    def _cache(self, fi: int) -> _ScanCache:
        c = self._scans.get(fi)
        if c is None:
            path = self.files[fi]
            try:
                f = h5py.File(path, "r")
            except OSError as exc:  # replaced or removed since the store was opened
                raise InputError(path, f"cannot open as HDF5 ({exc})") from None
            with f:
                g = f["scans"]
                c = _ScanCache(**{k: read_dataset(g, k, path) for k in _SCAN_CACHE_FIELDS})
            self._scans[fi] = c
        return c

    def scan(self, file: int, index: int) -> LaserScan:
        """Scan ``index`` of file ``file`` as a `LaserScan`."""
        c = self._cache(file)
        n = int(c.n_beams[index])
        return LaserScan(
            stamp=float(c.stamps[index]),
            ranges=c.ranges[index, :n],
            angle_min=float(c.angle_min[index]),
            angle_increment=float(c.angle_increment[index]),
            range_min=float(c.range_min[index]),
            range_max=float(c.range_max[index]),
        )

    def pair_scans(self, i: int) -> tuple[LaserScan, LaserScan, NDArray[np.float64]]:
        """``(previous scan, current scan, estimate)`` of pair ``i``."""
        r = self.records
        fi = int(r["file"][i])
        return (
            self.scan(fi, int(r["prev"][i])),
            self.scan(fi, int(r["curr"][i])),
            np.asarray(r["estimate"][i], dtype=np.float64),
        )

    def pair_points(
        self, i: int
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
        """``(previous points, current points, estimate)`` of pair ``i``.

        Points are float32 ``(M, 2)`` in each scan's sensor frame; the estimate maps the
        current points into the previous sensor frame.
        """
        prev, curr, est = self.pair_scans(i)
        return (
            np.asarray(prev.points(), dtype=np.float32),
            np.asarray(curr.points(), dtype=np.float32),
            est,
        )

    def aligned_points(self, i: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Previous points and current points moved by the estimate (previous frame)."""
        prev, curr, est = self.pair_points(i)
        return prev, np.asarray(transform_points(est, curr), dtype=np.float32)

    def summary(self) -> list[dict[str, Any]]:
        """Per-environment counts: rows with environment, split(s), sequences and labels."""
        r = self.records
        rows = []
        for env in self.environments:
            m = r["environment"] == env
            lab = r["label"][m]
            rows.append(
                {
                    "environment": env,
                    "splits": sorted(set(r["split"][m].tolist())),
                    "sequences": len(set(r["sequence"][m].tolist())),
                    "pairs": int(m.sum()),
                    "normal": int((lab == NORMAL).sum()),
                    "fault": int((lab == FAULT).sum()),
                    "ambiguous": int((lab == AMBIGUOUS).sum()),
                }
            )
        return rows


def merge_stores(
    sources: Iterable[str | Path], out_dir: str | Path, *, overwrite: bool = False
) -> Path:
    """Copy the sequence files of several stores into one directory with one manifest.

    The destination is written as a whole (`scanguard.fsutil.ResultDir`): a new folder, or
    the result of an earlier merge, replaced; an existing dataset or any other folder that
    a merge did not write is refused unless ``overwrite``.

    Args:
        sources: Dataset directories and/or pair files.
        out_dir: Destination directory.
        overwrite: Write into a folder that a merge did not create (files of the same names
            are replaced, other files kept).

    Returns:
        The destination directory.

    Raises:
        InputError: A source is invalid, two sources hold the same sequence id, or a
            sequence name cannot be a file name (``../../x``).
        OutputError: The destination is refused (see above), or the disk is full.
    """
    srcs = [Path(s) for s in sources]
    result = ResultDir(out_dir, overwrite=overwrite, record={"name": "scanguard dataset merge"})
    incomplete: list[tuple[Path, str]] = []
    files = _expand_sources(srcs, incomplete)
    store = PairStore(files, incomplete)  # validates formats and sequence-id uniqueness
    rels = []
    for fi, src in enumerate(files):  # every name checked before anything is written
        try:
            rels.append(sequence_file(str(store.file_attrs[fi]["sequence"])))
        except OutputError as exc:
            raise InputError(src, exc.problem) from None
    for path, why in incomplete:
        log.warning("%s: incomplete dataset build (%s); the merged store is incomplete", path, why)
    with result as tmp:
        (tmp / SEQUENCE_DIR).mkdir(parents=True, exist_ok=True)
        entries = []
        for fi, (src, rel) in enumerate(zip(files, rels, strict=True)):
            attrs = store.file_attrs[fi]
            shutil.copyfile(src, tmp / rel)
            lab = store.records["label"][store.records["file"] == fi]
            entries.append(
                {
                    "file": rel,
                    "environment": str(attrs["environment"]),
                    "sequence": str(attrs["sequence"]),
                    "split": str(attrs["split"]),
                    "pairs": int(lab.size),
                    "normal": int((lab == NORMAL).sum()),
                    "fault": int((lab == FAULT).sum()),
                    "ambiguous": int((lab == AMBIGUOUS).sum()),
                }
            )
        write_manifest(
            tmp,
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "merged_from": [str(s) for s in srcs],
                "complete": not incomplete,
                "pending": [{"source": str(path), "reason": why} for path, why in incomplete],
                "sequences": entries,
            },
        )
    return result.path
