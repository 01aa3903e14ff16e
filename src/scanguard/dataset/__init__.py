"""Labelled scan-pair datasets: build (simulation or recordings) and store (HDF5).

The torch `Dataset` over a store and the image helpers live with the detector
(`scanguard.detect.torch_data`, `scanguard.detect.images`); labels and the odometry model
with the pairs (`scanguard.pairs`).
"""

from __future__ import annotations

from scanguard.dataset.build import (
    BuildSummary,
    build_dataset,
    build_from_recording,
    build_from_recordings,
)
from scanguard.dataset.config import (
    DatasetConfig,
    DomainRandomization,
    EnvironmentSpec,
    SplitConfig,
)
from scanguard.dataset.labelling import label_sequence, simulated_odometry_steps
from scanguard.dataset.planning import plan_build, recording_digest
from scanguard.dataset.shards import SequenceRecords, read_sequence_file, write_sequence_file
from scanguard.dataset.stats import error_histograms, label_counts, write_stats
from scanguard.dataset.store import PairStore, merge_stores

__all__ = [
    "BuildSummary",
    "DatasetConfig",
    "DomainRandomization",
    "EnvironmentSpec",
    "PairStore",
    "SequenceRecords",
    "SplitConfig",
    "build_dataset",
    "build_from_recording",
    "build_from_recordings",
    "error_histograms",
    "label_counts",
    "label_sequence",
    "merge_stores",
    "plan_build",
    "read_sequence_file",
    "recording_digest",
    "simulated_odometry_steps",
    "write_sequence_file",
    "write_stats",
]
