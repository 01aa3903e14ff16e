"""One task of a build: one sequence or one recording labelled into its own shard.

The task functions (`sequence_task`, `recording_task`) are top-level and their arguments
picklable, so an executor (`scanguard.runtime.executor`) can run them in other processes or
on a Ray cluster; each writes only its own shard and updates the manifest under its lock.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scanguard.dataset.config import DatasetConfig
from scanguard.dataset.labelling import PairCallback, jsonable, label_sequence
from scanguard.dataset.manifest import update_manifest
from scanguard.dataset.manifest_steps import claim_name, find_built, recordings_manifest
from scanguard.dataset.planning import PlannedSequence, RecordingJob, safe_name
from scanguard.dataset.randomize import draw_domain, randomized_sequence, simulated_duration
from scanguard.dataset.shards import (
    SequenceRecords,
    sequence_file,
    shard_entry,
    write_sequence_file,
)
from scanguard.dataset.store import MANIFEST, read_manifest
from scanguard.errors import ConfigError, InputError, ScanGuardError
from scanguard.scan import ScanSequence

log = logging.getLogger(__name__)


def _simulate(item: PlannedSequence) -> ScanSequence:
    """Simulate a planned sequence; with ``randomize``, in its drawn domain.

    A randomised sequence carries its draw (and the resulting scan and pair counts) in
    ``metadata["domain"]``, which `build_sequence` stores in the file's meta.
    """
    from scanguard.sim import simulate

    env = item.environment
    spec = env.randomize
    if spec is None:
        seq = simulate(env.scenario, seed=item.seed, duration=env.duration, **env.overrides)
        if env.scan_stride > 1:
            seq = seq.subsequence(slice(None, None, env.scan_stride))
        return seq
    draw = draw_domain(spec, env.seed, item.index)
    # the draw wins over the same settings in the user's overrides (applied after them)
    overrides = {**env.overrides, **draw.overrides()}
    duration = simulated_duration(draw, spec, env.duration, env.scan_stride)
    seq = simulate(env.scenario, seed=item.seed, duration=duration, **overrides)
    if env.scan_stride > 1:
        seq = seq.subsequence(slice(None, None, env.scan_stride))
    seq, record = randomized_sequence(seq, draw, spec)
    record["simulated_duration"] = duration
    return seq


def _matcher(name: str) -> Callable[..., Any]:
    from scanguard.matching import get_matcher

    try:
        return get_matcher(name)
    except KeyError:
        raise ConfigError(f"unknown matcher {name!r}") from None


def build_sequence(
    item: PlannedSequence,
    config: DatasetConfig,
    fingerprint: str,
    out: Path,
    on_pair: PairCallback | None = None,
) -> dict[str, Any]:
    """Simulate, label and write one planned sequence; its manifest entry."""
    seq = _simulate(item)
    rec = label_sequence(
        seq,
        environment=item.environment.name,
        sequence=item.sequence,
        split=item.split,
        matcher=_matcher(config.matcher),
        matcher_name=config.matcher,
        initial_guess=config.initial_guess,
        labels=config.labels,
        odometry_noise=config.odometry_noise,
        gmapping=config.gmapping_score,
        meta={
            "scenario": item.environment.scenario,
            "seed": item.seed,
            "duration": item.environment.duration,
            "scan_stride": item.environment.scan_stride,
            "overrides": jsonable(item.environment.overrides),
            # only randomised sequences have it (older files' meta stays as it was)
            **({"domain": jsonable(seq.metadata["domain"])} if "domain" in seq.metadata else {}),
        },
        on_pair=on_pair,
    )
    rec.attrs["config_fingerprint"] = fingerprint
    write_sequence_file(out / item.file, rec)
    return shard_entry(rec, item.file)


@contextlib.contextmanager
def progress_bar(enabled: bool, total: int, what: str) -> Iterator[Callable[[int], None]]:
    """A progress callback: ``advance(n)`` after ``n`` more pairs."""
    # a bar on a terminal, log lines otherwise (a bar must never fill a log file)
    from scanguard.logging_utils import progress

    with progress(total, what, enabled=enabled) as advance:
        yield lambda n: advance(n)


@dataclass(frozen=True)
class SequenceTask:
    """One sequence of a simulated build, sent to a worker (picklable)."""

    item: PlannedSequence
    config: DatasetConfig
    fingerprint: str
    out: Path


def sequence_task(task: SequenceTask) -> dict[str, Any]:
    """Build one planned sequence into its own shard (top-level: spawn- and Ray-safe)."""
    return build_sequence(task.item, task.config, task.fingerprint, task.out)


def build_recording(
    job: RecordingJob, out: Path, cfg: DatasetConfig, *, progress: bool, overwrite: bool
) -> tuple[str, bool]:
    """Build one recording into ``out`` (inside a `build_session`).

    Returns:
        Its sequence name, and whether it was built (False: already there, resumed).
    """
    entries = read_manifest(out)["sequences"] if (out / MANIFEST).exists() else []
    known = find_built(out, job, entries, overwrite)
    if known is not None:
        update_manifest(out, lambda m: recordings_manifest(m, out, drop_pending=job.fingerprint))
        log.info("%s: already in %s as %s (resumed)", job.path, out, known)
        return known, False
    seq = _read_recording(job)
    base = safe_name(job.name or seq.name)
    claimed: dict[str, Any] = {}

    def claim(current: dict[str, Any]) -> dict[str, Any]:
        name, adopted = claim_name(current, out, job, base, overwrite)
        claimed.update(name=name, adopted=adopted)
        if adopted is not None:
            return recordings_manifest(current, out, drop_pending=job.fingerprint, entry=adopted)
        return recordings_manifest(current, out, add_pending=[job.pending(name)])

    update_manifest(out, claim)
    seq_name: str = claimed["name"]
    if claimed["adopted"] is not None:
        log.info("%s: found its finished file %s (resumed)", job.path, claimed["adopted"]["file"])
        return seq_name, False
    rel = sequence_file(seq_name)
    rec = _label_recording(seq, seq_name, job, cfg, progress=progress)
    write_sequence_file(out / rel, rec)
    entry = {**shard_entry(rec, rel), **job.entry_fields()}
    update_manifest(
        out, lambda m: recordings_manifest(m, out, drop_pending=job.fingerprint, entry=entry)
    )
    return seq_name, True


def _read_recording(job: RecordingJob) -> ScanSequence:
    """The recording's scans (its first ``max_scans``), refused without reference poses.

    Raises:
        InputError: The recording is unreadable or has no reference poses.
    """
    from scanguard.io import read_sequence

    seq = read_sequence(
        job.path,
        reference=job.reference,
        scan_topic=job.topics.get("scan_topic"),
        odom_topic=job.topics.get("odom_topic"),
        reference_topic=job.topics.get("reference_topic"),
        max_scans=job.max_scans,
    )
    if seq.reference is None:
        raise InputError(
            job.path, "recording has no reference poses; pass --reference TUM or --reference static"
        )
    if job.max_scans is not None:
        seq = seq.subsequence(slice(0, job.max_scans))
    return seq


def _label_recording(
    seq: ScanSequence, seq_name: str, job: RecordingJob, cfg: DatasetConfig, *, progress: bool
) -> SequenceRecords:
    """Label a recording's pairs as sequence ``seq_name`` (split ``heldout``), with its identity."""
    with progress_bar(progress, len(seq) - 1, f"recording {seq_name}") as advance:
        rec = label_sequence(
            seq,
            environment=seq_name,
            sequence=seq_name,
            split="heldout",
            matcher=_matcher(cfg.matcher),
            matcher_name=cfg.matcher,
            initial_guess=job.initial_guess,
            labels=cfg.labels,
            odometry_noise=cfg.odometry_noise,
            gmapping=cfg.gmapping_score,
            meta={
                "recording": str(job.path),
                "recording_sha256": job.digest,
                "reference_arg": job.reference,
                **({"topics": job.topics} if job.topics else {}),
            },
            on_pair=advance,
        )
    rec.attrs["config_fingerprint"] = job.fingerprint
    rec.attrs["recording_sha256"] = job.digest
    rec.attrs["options_fingerprint"] = job.options
    return rec


@dataclass(frozen=True)
class RecordingTask:
    """One recording of a build, sent to a worker (picklable)."""

    job: RecordingJob
    out: Path
    config: DatasetConfig
    overwrite: bool


def recording_task(task: RecordingTask) -> dict[str, Any]:
    """Build one recording into its own shard (top-level: spawn- and Ray-safe).

    Returns:
        ``{"sequence", "built"}``, or ``{"error"}`` with the one-line message of a
        `ScanGuardError` (a recording that cannot be read or labelled as asked). Anything
        else (a bug, a killed worker) propagates and leaves the recording pending.
    """
    from scanguard.runtime.executor import error_line

    try:
        name, was_built = build_recording(
            task.job, task.out, task.config, progress=False, overwrite=task.overwrite
        )
    except ScanGuardError as exc:
        return {"error": error_line(exc)}
    return {"sequence": name, "built": was_built}
