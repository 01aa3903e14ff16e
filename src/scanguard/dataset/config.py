"""Dataset build configuration (YAML, e.g. ``configs/paper.yaml``)."""

from __future__ import annotations

import hashlib
import json
from typing import Any, Literal

from pydantic import Field, model_validator

from scanguard.config import YamlModel
from scanguard.detect.labels import LabelConfig
from scanguard.detect.odometry import OdometryNoise

__all__ = [
    "DatasetConfig",
    "EnvironmentSpec",
    "InitialGuess",
    "OdometryNoise",
    "SplitConfig",
]

InitialGuess = Literal["identity", "odometry", "simulated_odometry", "auto"]


class EnvironmentSpec(YamlModel):
    """One simulated environment: several sequences of one scenario with different seeds.

    Attributes:
        name: Environment name in the store (e.g. ``"lobby"``).
        scenario: `scanguard.sim` scenario name.
        sequences: Number of sequences (sequence ``k`` is simulated with ``seed + k``).
        duration: Simulated time per sequence (s).
        scan_stride: Keep every ``scan_stride``-th scan (larger = larger motion per pair).
        seed: Base seed of the environment's sequences.
        heldout: Never part of train/val/test (e.g. the office Environment 5).
        overrides: Keyword overrides passed to ``simulate`` (crowd density, speed, ...).
    """

    name: str
    scenario: str
    sequences: int = Field(default=8, ge=1)
    duration: float = Field(default=25.0, gt=0)
    scan_stride: int = Field(default=1, ge=1)
    seed: int = 0
    heldout: bool = False
    overrides: dict[str, Any] = Field(default_factory=dict)


class SplitConfig(YamlModel):
    """Per-environment split of the (non-held-out) sequences, never of individual pairs.

    Attributes:
        val_sequences: Sequences per environment in ``"val"``.
        test_sequences: Sequences per environment in ``"test"``.
        seed: Seed of the (per-environment) shuffle that picks them.
    """

    val_sequences: int = Field(default=1, ge=0)
    test_sequences: int = Field(default=2, ge=0)
    seed: int = 0


class DatasetConfig(YamlModel):
    """A complete, reproducible dataset build.

    Attributes:
        name: Build name (written to the manifest).
        matcher: Registered matcher name (`scanguard.matching.MATCHERS`).
        initial_guess: Initial guess of simulated sequences: ``"identity"`` (the paper),
            ``"odometry"`` (the simulator's drifting odometry) or ``"simulated_odometry"``.
        recording_initial_guess: Initial guess for ``--recording`` builds; ``"auto"`` = what
            ``run`` gives its matcher by default (identity), so that ``run`` and ``dataset
            build`` label the same matches (`scanguard.dataset.build.resolve_initial_guess`).
        odometry_noise: Noise of simulated odometry.
        labels: Label thresholds.
        splits: Sequence-level split.
        gmapping_score: Also store the GMapping-style likelihood score of every match.
        environments: Simulated environments.
    """

    name: str = "dataset"
    matcher: str = "icp-paper"
    initial_guess: InitialGuess = "identity"
    recording_initial_guess: InitialGuess = "auto"
    odometry_noise: OdometryNoise = Field(default_factory=lambda: OdometryNoise())
    labels: LabelConfig = Field(default_factory=lambda: LabelConfig())
    splits: SplitConfig = Field(default_factory=lambda: SplitConfig())
    gmapping_score: bool = True
    environments: list[EnvironmentSpec] = Field(default_factory=list)

    @model_validator(mode="after")
    def _unique(self) -> DatasetConfig:
        names = [e.name for e in self.environments]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"duplicate environment names {sorted(dup)}")
        if self.initial_guess == "auto":
            raise ValueError("initial_guess 'auto' is for recordings only")
        return self

    def fingerprint(self) -> str:
        """Hash of everything that changes the stored data (resume refuses a mismatch)."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]
