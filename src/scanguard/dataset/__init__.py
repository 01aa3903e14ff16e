"""Labelled scan-pair datasets: build (simulation or recordings), store (HDF5), use (torch).

`PairDataset` needs torch and is imported lazily, so that ``import scanguard.dataset`` stays
light for tools that only read records.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from scanguard.dataset.build import (
    BuildSummary,
    build_dataset,
    build_from_recording,
    build_from_recordings,
    label_sequence,
    plan_build,
    recording_digest,
    simulated_odometry_steps,
)
from scanguard.dataset.config import (
    DatasetConfig,
    DomainRandomization,
    EnvironmentSpec,
    OdometryNoise,
    SplitConfig,
)
from scanguard.dataset.images import augment_pair, export_png, render_all
from scanguard.dataset.stats import error_histograms, label_counts, write_stats
from scanguard.dataset.store import (
    PairStore,
    SequenceRecords,
    merge_stores,
    read_sequence_file,
    write_sequence_file,
)
from scanguard.detect.labels import LabelConfig, assign_labels, pair_errors

if TYPE_CHECKING:
    from scanguard.dataset.torch_data import PairDataset

__all__ = [
    "BuildSummary",
    "DatasetConfig",
    "DomainRandomization",
    "EnvironmentSpec",
    "LabelConfig",
    "OdometryNoise",
    "PairDataset",
    "PairStore",
    "SequenceRecords",
    "SplitConfig",
    "assign_labels",
    "augment_pair",
    "build_dataset",
    "build_from_recording",
    "build_from_recordings",
    "error_histograms",
    "export_png",
    "label_counts",
    "label_sequence",
    "merge_stores",
    "pair_errors",
    "plan_build",
    "read_sequence_file",
    "recording_digest",
    "render_all",
    "simulated_odometry_steps",
    "write_sequence_file",
    "write_stats",
]


def __getattr__(name: str) -> Any:
    if name == "PairDataset":
        from scanguard.dataset.torch_data import PairDataset

        return PairDataset
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
