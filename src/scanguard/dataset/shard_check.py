"""The one validation of a pair file when a store opens it: names, shapes, indices.

A store is opened by every command that reads pairs (``dataset stats``, ``export-png``,
``evaluate``, ``calibrate``, ``train``); a file edited by hand or by another tool (a ``prev``
index past the scans, a ``label`` dataset missing or shorter than the others, an environment
named ``../x``) must fail there, in one line naming the file and the field, and never later
as an ``IndexError`` deep in rendering or as a PNG written outside the output folder.
`read_pair_table` reads a file's per-pair arrays once and checks them on the way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from scanguard.dataset.shards import PAIR_COLUMNS
from scanguard.errors import FormatError
from scanguard.fsutil import check_file_name
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL

#: Per-pair columns of shape ``(P, 3)`` (poses); every other column is ``(P,)``.
POSE_COLUMNS = ("estimate", "initial", "reference")
#: Per-scan datasets of shape ``(N,)`` under ``/scans`` (``ranges`` is ``(N, B)``).
SCAN_FIELDS = ("n_beams", "angle_min", "angle_increment", "range_min", "range_max", "stamps")
#: Extra per-pair columns that older files keep beside the metrics.
EXTRA_COLUMNS = ("iterations", "converged")


@dataclass
class PairTable:
    """The checked per-pair arrays and names of one pair file.

    Attributes:
        environment: Environment name (a plain file name).
        sequence: Sequence id (a plain file name).
        split: Split name.
        n_scans: Scans in ``/scans``.
        columns: The `PAIR_COLUMNS` and the `EXTRA_COLUMNS` present outside the metrics.
        metrics: One ``(P,)`` array per metric.
    """

    environment: str
    sequence: str
    split: str
    n_scans: int
    columns: dict[str, NDArray[Any]] = field(default_factory=dict)
    metrics: dict[str, NDArray[Any]] = field(default_factory=dict)


def read_dataset(node: Any, name: str, path: Path) -> NDArray[Any]:
    """``node[name]`` read whole.

    Raises:
        FormatError: The dataset is missing, not an array, or unreadable (a corrupt chunk);
            names ``path`` and the dataset.
    """
    if name not in node or not isinstance(node[name], h5py.Dataset):
        raise FormatError(path, f"pair file lacks the {node.name.rstrip('/')}/{name} dataset")
    try:
        return np.asarray(node[name][()])
    except (OSError, ValueError, TypeError) as exc:
        detail = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise FormatError(
            path, f"cannot read {node.name.rstrip('/')}/{name}: corrupt HDF5 data ({detail})"
        ) from None


def _name_attr(f: h5py.File, key: str, path: Path, *, file_name: bool) -> str:
    value = f.attrs.get(key)
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if not isinstance(value, str):
        raise FormatError(path, f"pair file attribute {key!r} is missing or not a string")
    if file_name:  # it names a folder or a file of export-png, merge, run-many
        try:
            check_file_name(value, f"{key} name")
        except ValueError as exc:
            raise FormatError(path, str(exc)) from None
    return value


def _check_length(name: str, arr: NDArray[Any], n: int, path: Path, *, width: int = 0) -> None:
    shape = (n, width) if width else (n,)
    if arr.shape != shape:
        raise FormatError(
            path,
            f"{name} has shape {arr.shape}, expected {shape} (one row per "
            f"{'pair' if 'pairs' in name else 'scan'})",
        )


def _check_indices(name: str, arr: NDArray[Any], n_scans: int, path: Path) -> None:
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise FormatError(path, f"{name} holds {arr.dtype} values, not scan indices")
    bad = (arr < 0) | (arr >= n_scans)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(
            path,
            f"{name}[{i}] = {int(arr[i])} is not a scan index (the file has {n_scans} scans); "
            f"{int(bad.sum())} such pair(s)",
        )


def _check_scans(f: h5py.File, path: Path) -> int:
    """Check ``/scans``; return its number of scans."""
    if "scans" not in f or not isinstance(f["scans"], h5py.Group):
        raise FormatError(path, "pair file lacks the /scans group")
    g = f["scans"]
    ranges = g.get("ranges")
    if not isinstance(ranges, h5py.Dataset) or len(ranges.shape) != 2:
        raise FormatError(path, "/scans/ranges is missing or not a 2-D array")
    n, width = (int(v) for v in ranges.shape)
    beams = read_dataset(g, "n_beams", path)
    _check_length("/scans/n_beams", beams, n, path)
    if beams.size and (beams.min() < 0 or beams.max() > width):
        raise FormatError(path, f"/scans/n_beams holds counts outside 0..{width} (ranges width)")
    for name in SCAN_FIELDS[1:]:
        _check_length(f"/scans/{name}", read_dataset(g, name, path), n, path)
    for name in ("reference", "odometry"):
        if name in g:
            _check_length(f"/scans/{name}", read_dataset(g, name, path), n, path, width=3)
    offset = np.asarray(f.attrs.get("laser_offset", np.zeros(0)))
    if offset.shape != (3,):
        raise FormatError(path, f"attribute 'laser_offset' has shape {offset.shape}, expected (3,)")
    return n


def _pair_count(columns: dict[str, NDArray[Any]], path: Path) -> int:
    """The number of pairs: the length most columns agree on; the others are named."""
    lengths = {name: int(arr.shape[0]) if arr.ndim else -1 for name, arr in columns.items()}
    values = list(lengths.values())
    n = max(set(values), key=lambda v: (values.count(v), v))
    odd = [f"{name} {k}" for name, k in lengths.items() if k != n]
    if odd:
        raise FormatError(
            path,
            f"/pairs datasets differ in length: {', '.join(odd)} rows where the others have {n}",
        )
    return n


def read_pair_table(f: h5py.File, path: Path) -> PairTable:
    """Read and check the names and per-pair arrays of an open pair file.

    Checked: the environment and sequence names are plain file names; ``/scans`` arrays
    have one row per scan; every `PAIR_COLUMNS` dataset and every metric has one row per
    pair (poses three columns); ``prev`` and ``curr`` are scan indices of the file; labels
    are -1, 0 or 1.

    Raises:
        FormatError: A name, a shape, an index or a label is wrong, a dataset is missing, or
            the HDF5 data cannot be read (a corrupt chunk); the message names ``path`` and
            the field.
    """
    table = PairTable(
        environment=_name_attr(f, "environment", path, file_name=True),
        sequence=_name_attr(f, "sequence", path, file_name=True),
        split=_name_attr(f, "split", path, file_name=False),
        n_scans=_check_scans(f, path),
    )
    if "pairs" not in f or not isinstance(f["pairs"], h5py.Group):
        raise FormatError(path, "pair file lacks the /pairs group")
    pg = f["pairs"]
    for name in PAIR_COLUMNS:
        table.columns[name] = read_dataset(pg, name, path)
    n = _pair_count(table.columns, path)
    for name, arr in table.columns.items():
        _check_length(f"/pairs/{name}", arr, n, path, width=3 if name in POSE_COLUMNS else 0)
    label = table.columns["label"]
    if not np.isin(label, (NORMAL, FAULT, AMBIGUOUS)).all():
        raise FormatError(path, "/pairs/label holds values other than -1, 0 and 1")
    for name in ("prev", "curr"):
        _check_indices(f"/pairs/{name}", table.columns[name], table.n_scans, path)
    metrics = pg.get("metrics")
    if not isinstance(metrics, h5py.Group):
        raise FormatError(path, "pair file lacks the /pairs/metrics group")
    for name in EXTRA_COLUMNS:
        if name in pg and name not in metrics:
            table.columns[name] = read_dataset(pg, name, path)
            _check_length(f"/pairs/{name}", table.columns[name], n, path)
    for name in metrics:
        table.metrics[name] = read_dataset(metrics, name, path)
        _check_length(f"/pairs/metrics/{name}", table.metrics[name], n, path)
    return table
