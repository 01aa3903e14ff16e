"""Planning a build: which sequences, with which seeds and splits, and what identifies them.

A simulated build is planned from its config alone (`plan_build`): every sequence's seed
and split follow from the config, so an interrupted build resumes to exactly the data an
uninterrupted one writes. A recording is identified by its content (`recording_digest`)
plus the build options, never by its file name (`RecordingJob.fingerprint`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scanguard.dataset.config import DatasetConfig, EnvironmentSpec, InitialGuess
from scanguard.dataset.labelling import name_seed
from scanguard.dataset.shards import sequence_file
from scanguard.errors import InputError
from scanguard.safeload import check_input_file


@dataclass(frozen=True)
class PlannedSequence:
    """One sequence of a simulated build."""

    environment: EnvironmentSpec
    index: int
    sequence: str
    split: str
    seed: int

    @property
    def file(self) -> str:
        """Path of its file relative to the build directory."""
        return sequence_file(self.sequence)


def plan_build(config: DatasetConfig) -> list[PlannedSequence]:
    """All sequences of a simulated build with their seeds and splits (by sequence).

    Splits are drawn per environment with a seeded shuffle of the sequence indices: the first
    ``test_sequences`` go to ``"test"``, the next ``val_sequences`` to ``"val"``, the rest to
    ``"train"``; held-out environments are ``"heldout"`` entirely.
    """
    plan = []
    sp = config.splits
    for env in config.environments:
        splits = ["heldout"] * env.sequences
        if not env.heldout:
            order = np.random.default_rng(name_seed(env.name, sp.seed)).permutation(env.sequences)
            n_test = min(sp.test_sequences, env.sequences)
            n_val = min(sp.val_sequences, env.sequences - n_test)
            splits = ["train"] * env.sequences
            for rank, k in enumerate(order.tolist()):
                if rank < n_test:
                    splits[k] = "test"
                elif rank < n_test + n_val:
                    splits[k] = "val"
        for k in range(env.sequences):
            plan.append(
                PlannedSequence(
                    environment=env,
                    index=k,
                    sequence=f"{env.name}_{k:02d}",
                    split=splits[k],
                    seed=env.seed + k,
                )
            )
    return plan


def expected_pairs(item: PlannedSequence) -> int:
    """About how many pairs a planned sequence has (for the progress total)."""
    # the progress total only; the simulator's exact scan count may differ by one
    env = item.environment
    stride = int(env.overrides.get("stride", 1)) * env.scan_stride
    return max(1, int(env.duration * 10.0 / stride))


_HASH_CHUNK = 1 << 20


def _hash_file(h: Any, path: Path) -> None:
    with path.open("rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            h.update(chunk)


def recording_digest(path: str | Path) -> str:
    """SHA-256 of a recording's bytes: its content identity in a build directory.

    A bag folder (ROS 2) hashes every file in it with its relative name, in sorted order.

    Raises:
        InputError: The recording is missing, unreadable, or a FIFO, device or socket (the
            input-path check of every reader: hashing one would block or never end).
    """
    from scanguard.io import check_recording_path

    p = check_recording_path(path)
    h = hashlib.sha256()
    try:
        if p.is_dir():
            for f in sorted(q for q in p.rglob("*") if q.is_file()):
                h.update(f.relative_to(p).as_posix().encode() + b"\0")
                _hash_file(h, f)
        elif p.exists():
            _hash_file(h, p)
        else:
            raise InputError(p, "file not found")
    except OSError as exc:
        raise InputError(p, f"cannot read ({exc.strerror or exc})") from None
    return h.hexdigest()


@dataclass(frozen=True)
class RecordingJob:
    """One recording to add to a build directory, with its identity.

    The identity is the content (`recording_digest`) plus the build options; the file name
    only suggests the sequence name.
    """

    path: Path
    source: str
    digest: str
    options: str
    legacy: str
    name: str | None
    reference: str | None
    initial_guess: InitialGuess
    max_scans: int | None
    topics: dict[str, str] = field(default_factory=dict)

    @property
    def fingerprint(self) -> str:
        """Hash of the content and the options (the files' ``config_fingerprint``)."""
        blob = json.dumps({"options": self.options, "recording": self.digest}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def pending(self, sequence: str | None = None) -> dict[str, Any]:
        """The manifest's ``pending`` item of this recording."""
        item: dict[str, Any] = {"recording": self.source, "fingerprint": self.fingerprint}
        if sequence is not None:
            item["sequence"] = sequence
        return item

    def entry_fields(self) -> dict[str, Any]:
        """Identity fields added to its manifest entry."""
        return {
            "recording": self.source,
            "recording_sha256": self.digest,
            "options_fingerprint": self.options,
            "fingerprint": self.fingerprint,
        }


def recording_job(
    path: str | Path,
    cfg: DatasetConfig,
    *,
    reference: str | None,
    name: str | None,
    initial_guess: InitialGuess | None,
    max_scans: int | None,
    topics: dict[str, str],
) -> RecordingJob:
    """A recording's job: its content digest and the fingerprints of the build options.

    Raises:
        InputError: The recording (or a TUM reference file) is missing or unreadable.
    """
    p = Path(path)
    mode = initial_guess or cfg.recording_initial_guess
    ref_digest = None
    if reference is not None and str(reference).lower() != "static":
        # a FIFO or a device is refused here, before its bytes are hashed (never ends)
        ref_digest = recording_digest(check_input_file(reference, what="TUM reference file"))
    common = {
        "matcher": cfg.matcher,
        "labels": cfg.labels.model_dump(mode="json"),
        "odometry_noise": cfg.odometry_noise.model_dump(mode="json"),
        "gmapping_score": cfg.gmapping_score,
        "initial_guess": mode,
        "max_scans": max_scans,
    }
    options = {
        **common,
        "topics": dict(sorted(topics.items())),
        "reference": None if reference is None else ("static" if ref_digest is None else "tum"),
        "reference_sha256": ref_digest,
    }
    # what builds before content identity hashed (the file name stood for the recording)
    legacy = {**common, "reference": reference, "recording": p.name, **topics}
    return RecordingJob(
        path=p,
        source=str(p.resolve()),
        digest=recording_digest(p),
        options=_short_hash(options),
        legacy=_short_hash(legacy),
        name=name,
        reference=reference,
        initial_guess=mode,
        max_scans=max_scans,
        topics=dict(topics),
    )


def _short_hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def safe_name(name: str) -> str:
    """``name`` reduced to characters safe in a file name (the sequence name of a recording)."""
    keep = [c if (c.isalnum() or c in "-_.") else "_" for c in name]
    return "".join(keep).strip("._") or "recording"
