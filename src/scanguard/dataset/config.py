"""Dataset build configuration (YAML, e.g. ``configs/paper.yaml``)."""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any, Literal

from pydantic import (
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
    model_validator,
)

from scanguard.config import YamlModel
from scanguard.fsutil import check_file_name
from scanguard.pairs.labels import LabelConfig
from scanguard.pairs.odometry import OdometryNoise

__all__ = [
    "DatasetConfig",
    "EnvironmentSpec",
    "InitialGuess",
    "SplitConfig",
]

InitialGuess = Literal["identity", "odometry", "simulated_odometry", "auto"]

#: A closed range ``(low, high)`` of floats; a draw is uniform (or log-uniform) within it.
FloatRange = tuple[float, float]
#: A closed range ``(low, high)`` of integers.
IntRange = tuple[int, int]


def _check_pair(name: str, value: tuple[float, float], low: float, high: float) -> None:
    """Raise ValueError naming ``name`` unless ``low <= value[0] <= value[1] <= high``."""
    lo, hi = value
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} [{lo}, {hi}] must be finite")
    if lo > hi:
        raise ValueError(f"{name} [{lo}, {hi}] is reversed: give [low, high] with low <= high")
    if lo < low or hi > high:
        raise ValueError(f"{name} [{lo}, {hi}] must lie within [{low}, {high}]")


class DomainRandomization(YamlModel):
    """Per-sequence randomisation of the sensing domain (a detector that transfers).

    Every sequence of an environment with ``randomize`` draws its own laser (beams, field of
    view, maximum range, scan rate, range noise, dropouts) and, for a fraction of the
    sequences, a CARMEN-style thinning (a scan is kept only after the robot travelled about
    ``d`` metres or turned about ``a`` degrees since the last kept one). The draw depends
    only on ``seed``, the environment's ``seed`` and the sequence index (see
    `scanguard.dataset.randomize.draw_domain`), so a build stays reproducible and resumable,
    and it is stored in each sequence file's ``meta["domain"]``.

    Ranges are ``[low, high]`` pairs (``low == high`` fixes a value). Rates and maximum
    ranges are drawn log-uniformly (real sensors spread over orders of magnitude: 5 m
    indoor scanners next to 80 m SICKs), everything else uniformly.

    Attributes:
        n_beams: Beams per scan.
        fov_deg: Field of view (deg), centred on the sensor's x axis.
        range_max: Maximum range (m); longer returns are "no return".
        rate_hz: Scan rate (Hz) of unthinned sequences: the rate of the scans that are
            matched (the scenario's ``stride`` is replaced by 1; the environment's
            ``scan_stride`` still applies on top).
        noise_std: Constant part of the range noise std (m).
        noise_rel: Range-proportional part of the range noise std (std = ``noise_std +
            noise_rel * range``).
        dropout_prob: Probability that a beam returns nothing.
        thinned_fraction: Probability that a sequence is thinned like a CARMEN log.
        thin_rate_hz: Scan rate (Hz) of the scanner before thinning (the steps are only
            "about d" when the scanner is much faster than the robot's motion per scan).
        thin_distance: ``d``: distance (m) travelled before the next scan is kept.
        thin_angle_deg: ``a``: rotation (deg) before the next scan is kept.
        max_pairs: Most pairs per sequence: fast rates shorten the simulated duration to
            ``max_pairs / rate`` seconds and any longer sequence is cut (matching, not
            simulation, is the expensive part of a build).
        seed: Extra seed of the draws (change it to redraw the domains of the same worlds).
    """

    n_beams: IntRange = (180, 1440)
    fov_deg: FloatRange = (180.0, 360.0)
    range_max: FloatRange = (4.0, 80.0)
    rate_hz: FloatRange = (1.0, 40.0)
    noise_std: FloatRange = (0.0, 0.03)
    noise_rel: FloatRange = (0.0, 0.01)
    dropout_prob: FloatRange = (0.0, 0.1)
    thinned_fraction: float = Field(default=0.25, ge=0.0, le=1.0)
    thin_rate_hz: FloatRange = (10.0, 40.0)
    thin_distance: FloatRange = (0.5, 1.2)
    thin_angle_deg: FloatRange = (15.0, 30.0)
    max_pairs: int = Field(default=500, ge=1, le=100_000)
    seed: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _ranges(self) -> DomainRandomization:
        # physical limits: those of the simulator's SensorConfig / ScenarioConfig fields, and
        # range_max above every preset's range_min (0.15 m) so a drawn sensor is valid
        lo_b, hi_b = self.n_beams
        _check_pair("n_beams", (float(lo_b), float(hi_b)), 2.0, 10_000.0)
        for name, low, high in (
            ("fov_deg", 1.0, 360.0),
            ("range_max", 0.5, 1000.0),
            ("rate_hz", 0.1, 100.0),
            ("noise_std", 0.0, 10.0),
            ("noise_rel", 0.0, 1.0),
            ("dropout_prob", 0.0, 1.0),
            ("thin_rate_hz", 0.1, 100.0),
            ("thin_distance", 0.01, 100.0),
            ("thin_angle_deg", 0.1, 360.0),
        ):
            _check_pair(name, getattr(self, name), low, high)
        return self


MAX_SEQUENCES = 10_000
"""Most sequences per environment (a few hundred make a large dataset)."""

MAX_DURATION_S = 86_400.0
"""Longest simulated sequence (s): a day."""


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
        randomize: Draw each sequence's sensing domain (`DomainRandomization`); the drawn
            values replace the same settings of ``overrides``. None (default): every
            sequence uses the scenario's sensor, as before.
    """

    name: str
    scenario: str
    # upper bounds: a typo (1000000000) is refused up front, not after allocating gigabytes
    sequences: int = Field(default=8, ge=1, le=MAX_SEQUENCES)
    duration: float = Field(default=25.0, gt=0, le=MAX_DURATION_S)
    scan_stride: int = Field(default=1, ge=1, le=1000)
    seed: int = 0
    heldout: bool = False
    overrides: dict[str, Any] = Field(default_factory=dict)
    randomize: DomainRandomization | None = None

    @field_validator("name")
    @classmethod
    def _file_name(cls, name: str) -> str:
        # the name becomes the shard's file name: "../../victim" must never leave -o
        return check_file_name(name, "environment name")

    @model_serializer(mode="wrap")
    def _drop_unset_randomize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # without randomisation the dump (hence `DatasetConfig.fingerprint` and every saved
        # config.yaml) is exactly what it was before the field existed, so existing builds
        # keep resuming
        data: dict[str, Any] = handler(self)
        if data.get("randomize", 0) is None:
            del data["randomize"]
        return data


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
            build`` label the same matches (`scanguard.dataset.labelling.resolve_initial_guess`).
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
