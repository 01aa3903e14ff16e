"""Pinned counts of a small reference build of the paper dataset (issue 15).

The shipped model (``src/scanguard/models/default.pt``) was trained on the labels that
``scanguard dataset build --config configs/paper.yaml`` produced, and README.md and
docs/model_card.md document that build's normal / fault / ambiguous counts. A change to the
simulator, the matcher, the initial guess or the labelling rule changes those labels under the
shipped model. This test rebuilds a small but representative version of the paper dataset
(every environment of ``configs/paper.yaml``, its matcher, initial guess, labelling rule,
stride and GMapping score; only fewer and shorter sequences) with the real build code, and
pins the exact counts per environment and checksums of the stored labels and of the matched
poses (rounded to 1e-6 m / rad, so that the last float bit does not matter).

When these values change **on purpose**: rebuild the paper dataset
(``scanguard dataset build --config configs/paper.yaml``), retrain the shipped model on it,
re-document the counts (README.md, docs/model_card.md, docs/dataset.md) and only then update
the values below (run this file and copy what it reports). When they change by accident, the
change broke the dataset the shipped model was trained on.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scanguard.dataset import DatasetConfig, PairStore, build_dataset

PAPER = Path(__file__).resolve().parents[1] / "configs" / "paper.yaml"
#: Sequences per environment (the held-out office: 1) and seconds each.
SEQUENCES = 2
DURATION = 24.0

#: (normal, fault, ambiguous) per environment of the reference build.
PINNED_COUNTS: dict[str, tuple[int, int, int]] = {
    "corridor": (153, 64, 23),
    "glass": (107, 91, 42),
    "hall": (39, 174, 27),
    "lobby": (178, 44, 18),
    "office": (68, 27, 25),
}
#: sha256 (first 16 hex digits) of the stored labels (int8, store order).
PINNED_LABELS = "52cdf95d345311ae"
#: sha256 (first 16 hex digits) of the matched poses in micro-units (int64, store order).
PINNED_POSES = "75cdb906428e40bd"


def reference_config() -> DatasetConfig:
    """``configs/paper.yaml`` with fewer, shorter sequences (everything else unchanged)."""
    data = DatasetConfig.from_yaml(PAPER).model_dump(mode="json")
    for env in data["environments"]:
        env["sequences"] = 1 if env.get("heldout") else SEQUENCES
        env["duration"] = DURATION
    data["name"] = "paper-pinned"
    data["splits"] = {"val_sequences": 0, "test_sequences": 1, "seed": 0}
    return DatasetConfig.from_dict(data)


def summary(out: Path) -> dict[str, Any]:
    """Counts per environment and the label / pose checksums of a build directory."""
    r = PairStore.open(out).records
    env = np.asarray(r["environment"]).astype(str)
    label = np.asarray(r["label"])
    counts = {
        e: tuple(int(np.sum(label[env == e] == v)) for v in (0, 1, -1))
        for e in sorted(set(env.tolist()))
    }
    poses = np.rint(np.asarray(r["estimate"], dtype=np.float64) * 1e6).astype(np.int64)
    return {
        "counts": counts,
        "labels": hashlib.sha256(label.astype(np.int8).tobytes()).hexdigest()[:16],
        "poses": hashlib.sha256(np.ascontiguousarray(poses).tobytes()).hexdigest()[:16],
    }


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("pinned") / "paper"
    build_dataset(reference_config(), out, progress=False, workers=1)
    return summary(out)


def test_reference_build_keeps_its_counts(reference: dict[str, Any]) -> None:
    assert reference["counts"] == PINNED_COUNTS, (
        "the paper dataset's labels changed: if on purpose, rebuild data/paper, retrain the "
        "shipped model and re-document the counts (see this module's docstring)"
    )


def test_reference_build_keeps_its_labels_and_poses(reference: dict[str, Any]) -> None:
    assert (reference["labels"], reference["poses"]) == (PINNED_LABELS, PINNED_POSES)


def test_reference_build_is_independent_of_workers(
    reference: dict[str, Any], tmp_path: Path
) -> None:
    build_dataset(reference_config(), tmp_path / "two", progress=False, workers=2)
    assert summary(tmp_path / "two") == reference
