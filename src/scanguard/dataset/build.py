"""Build labelled pair datasets: match every consecutive pair, compare with the reference, store.

The drivers of a build (`build_dataset`, `build_from_recordings`): they plan, resume, run
one task per sequence or recording (`scanguard.dataset.tasks`; in this process or on an
executor) and keep the manifest.

A build directory holds ``sequences/<sequence>.h5`` (one file per sequence, each written
atomically), ``manifest.json`` (rewritten atomically, under a file lock, after every finished
sequence) and the resolved ``config.yaml``. Every sequence depends only on the config and its
own seed, so an interrupted build resumes by skipping the files that already exist and ends
with exactly the data an uninterrupted build would have written. Until then the manifest says
``complete: false`` and lists the ``pending`` work.

Recordings are identified by their content (a SHA-256 of the file) plus the build options,
never by their file name (see `build_from_recordings`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanguard.config import save_config
from scanguard.dataset.config import DatasetConfig, InitialGuess
from scanguard.dataset.manifest import build_session, update_manifest
from scanguard.dataset.manifest_steps import (
    drop_pending,
    manifest_entries,
    order_new_entries,
    recordings_manifest,
    simulated_manifest,
)
from scanguard.dataset.planning import (
    PlannedSequence,
    RecordingJob,
    expected_pairs,
    plan_build,
    recording_job,
)
from scanguard.dataset.shards import inspect_shard, warn_corrupt
from scanguard.dataset.store import MANIFEST, read_manifest
from scanguard.dataset.tasks import (
    RecordingTask,
    SequenceTask,
    build_recording,
    build_sequence,
    progress_bar,
    recording_task,
    sequence_task,
)
from scanguard.errors import ConfigError, ScanGuardError

if TYPE_CHECKING:
    from scanguard.runtime.executor import Executor

log = logging.getLogger(__name__)


@dataclass
class BuildSummary:
    """What a build did.

    Attributes:
        out_dir: The build directory.
        built: Sequences built in this run.
        skipped: Sequences already present (resumed).
        entries: Manifest entries of all sequences of the directory (a simulated build's
            in plan order, then those other builds added).
        complete: Nothing is pending in the directory (its manifest's ``complete``).
        failed: Sequences (simulated) or recordings that failed in this run, with their
            one-line error (only where the build goes on past failures: an executor).
    """

    out_dir: Path
    built: list[str]
    skipped: list[str]
    entries: list[dict[str, Any]]
    complete: bool = True
    failed: dict[str, str] = field(default_factory=dict)

    def totals(self) -> dict[str, int]:
        """Summed pair counts."""
        keys = ("pairs", "normal", "fault", "ambiguous")
        return {k: sum(int(e.get(k, 0)) for e in self.entries) for k in keys}


def build_dataset(
    config: DatasetConfig,
    out_dir: str | Path,
    *,
    progress: bool = True,
    overwrite: bool = False,
    max_sequences: int | None = None,
    workers: int = 1,
    executor: Executor | None = None,
) -> BuildSummary:
    """Simulate, match, label and store every sequence of ``config`` (resumable).

    Resuming keeps the finished sequence files (a corrupt one is reported and rebuilt),
    removes the temporary files of killed writes, and keeps what ``--recording`` builds added
    to the same directory. The manifest is updated under a file lock after every sequence
    and says ``complete: false`` (with the ``pending`` sequences) until every sequence is
    built. ``config.yaml`` is written only once the build is accepted.

    Args:
        config: The build.
        out_dir: Build directory (created).
        progress: Show a progress bar.
        overwrite: Rebuild sequence files made with a different config instead of failing.
        max_sequences: Stop after building this many new sequences (for tests of resuming).
        workers: Processes building sequences in parallel (1 = in this process); used
            when no ``executor`` is given.
        executor: Where the sequences are built, one task each
            (`scanguard.runtime.executor`: a local process pool or Ray). A failing task
            costs only its sequence: it is listed in ``BuildSummary.failed``, stays pending
            in the manifest, and a rerun builds it.

    Returns:
        A `BuildSummary`.

    Raises:
        ConfigError: The directory or an existing sequence file was built with another
            config (and not ``overwrite``), or the config has no environments.
        InputError: The directory cannot be used (not a directory, malformed manifest).
    """
    if not config.environments:
        raise ConfigError(f"dataset config {config.name!r} has no environments to simulate")
    out = Path(out_dir)
    fp = config.fingerprint()
    plan = plan_build(config)
    with build_session(out):
        done, todo = _resume(out, plan, fp, overwrite=overwrite)
        # only now: a refused build must leave the config of the data in place
        save_config(config, out)
        if max_sequences is not None:
            todo = todo[:max_sequences]
        skipped = list(done)
        log.info("%s: %d sequences to build, %d already done", out, len(todo), len(skipped))

        def record() -> dict[str, Any]:
            return update_manifest(
                out, lambda current: simulated_manifest(current, out, config, plan, done)
            )

        record()
        built, failed = _build_sequences(
            todo,
            config,
            fp,
            out,
            done,
            record,
            pool=_pool(executor, workers, len(todo)),
            progress=progress,
        )
        manifest = record()
    return BuildSummary(
        out_dir=out,
        built=built,
        skipped=skipped,
        entries=list(manifest["sequences"]),
        complete=bool(manifest["complete"]),
        failed=failed,
    )


def _resume(
    out: Path, plan: list[PlannedSequence], fp: str, *, overwrite: bool
) -> tuple[dict[str, dict[str, Any]], list[PlannedSequence]]:
    """The planned sequences already built (their entries) and those to build.

    Raises:
        ConfigError: The directory or a sequence file was built with another config (and
            not ``overwrite``).
    """
    old = read_manifest(out) if (out / MANIFEST).exists() else {}
    old_fp = old.get("config_fingerprint")
    if old_fp is not None and old_fp != fp and not overwrite:
        raise ConfigError(
            f"{out / MANIFEST}: built with another config (fingerprint {old_fp}, now {fp}); "
            "use another output directory or --overwrite"
        )
    done: dict[str, dict[str, Any]] = {}
    todo: list[PlannedSequence] = []
    for item in plan:
        path = out / item.file
        if path.exists():
            state = inspect_shard(path, item.file)
            if not state.ok:
                warn_corrupt(path, state)
            elif state.fingerprint == fp and state.entry is not None:
                done[item.sequence] = state.entry
                continue
            elif not overwrite:
                raise ConfigError(
                    f"{path}: built with another config (fingerprint {state.fingerprint}, "
                    f"now {fp}); use another output directory or --overwrite"
                )
        todo.append(item)
    return done, todo


def _pool(executor: Executor | None, workers: int, n_tasks: int) -> Executor | None:
    """Where the sequences are built: None in this process, else an executor."""
    if executor is None and (workers <= 1 or n_tasks <= 1):
        return None
    from scanguard.runtime.executor import LocalExecutor

    return executor if executor is not None else LocalExecutor(workers)


def _build_sequences(
    todo: list[PlannedSequence],
    config: DatasetConfig,
    fp: str,
    out: Path,
    done: dict[str, dict[str, Any]],
    record: Callable[[], Any],
    pool: Executor | None,
    progress: bool,
) -> tuple[list[str], dict[str, str]]:
    """Build the sequences (``done`` gets their entries, the manifest is kept after each).

    Returns:
        The sequences built, and those that failed with their one-line error (an executor
        goes on past failures; in this process the first one is raised).
    """
    built: list[str] = []
    failed: dict[str, str] = {}
    total_pairs = sum(expected_pairs(p) for p in todo)
    with progress_bar(progress, total_pairs, f"dataset {config.name}") as advance:
        if pool is None:
            for item in todo:
                done[item.sequence] = build_sequence(item, config, fp, out, advance)
                built.append(item.sequence)
                record()
            return built, failed
        tasks = [SequenceTask(it, config, fp, out) for it in todo]
        for task, outcome in pool.map(sequence_task, tasks):
            item = task.item
            advance(expected_pairs(item))
            if not outcome.ok or outcome.value is None:
                # its shard only: the others go on, a rerun builds it (still pending)
                failed[item.sequence] = outcome.error or "no result"
                log.error("%s: failed: %s", item.sequence, failed[item.sequence])
                continue
            done[item.sequence] = outcome.value
            built.append(item.sequence)
            record()
    return built, failed


def build_from_recordings(
    paths: Sequence[str | Path],
    out_dir: str | Path,
    config: DatasetConfig | None = None,
    *,
    reference: str | None = None,
    initial_guess: InitialGuess | None = None,
    max_scans: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
    names: Sequence[str | None] | None = None,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    reference_topic: str | None = None,
    executor: Executor | None = None,
) -> BuildSummary:
    """Label every consecutive pair of several recordings; add them to a build directory.

    Each recording is identified by its content (`recording_digest`) and the build options,
    not by its file name: a recording already built is skipped (resumed), a changed one is
    rebuilt under its old name, and a different recording whose name is taken gets a name
    with its hash. All recordings are registered as ``pending`` in the manifest before the
    first is built, so an interrupted build says ``complete: false`` until a rerun finishes
    them. The manifest is updated under a file lock, so concurrent builds into one directory
    keep each other's recordings.

    Args:
        paths: Recordings readable by `scanguard.io.read_sequence`.
        out_dir: Build directory.
        config: Matcher, labels, odometry noise (environments are ignored).
        reference: TUM file or ``"static"`` (passed to ``read_sequence``) for every recording.
        initial_guess: Override ``config.recording_initial_guess``.
        max_scans: Use only the first scans of each (quick looks, tests).
        progress: Show a progress bar.
        overwrite: Replace a recording's file built with other settings.
        names: Environment/sequence name per recording (None: from the recording).
        scan_topic: LaserScan topic (CARMEN: laser message type), for every recording.
        odom_topic: Odometry topic, for every recording.
        reference_topic: Reference pose topic, for every recording.
        executor: Build the recordings as tasks of this executor
            (`scanguard.runtime.executor`), each into its own shard; a recording that fails
            is reported in ``BuildSummary.failed`` and the others finish. None: one after the
            other in this process, the first failure raised.

    Returns:
        A `BuildSummary` of the whole directory; ``built``, ``skipped`` and ``failed`` cover
        every recording of this call (``entries`` in the order of ``paths``).

    Raises:
        InputError: A recording is missing, unreadable or has no reference.
        ConfigError: A recording was built here with other settings (not ``overwrite``).
    """
    cfg = config or DatasetConfig()
    out = Path(out_dir)
    names = _names(paths, names)
    topics = _topics(scan_topic, odom_topic, reference_topic)
    # every recording checked and hashed before the folder is made: a missing one, a FIFO
    # or a device leaves nothing behind
    jobs = _jobs(paths, names, cfg, topics, reference, initial_guess, max_scans)
    with build_session(out):
        before = {str(e.get("sequence")) for e in manifest_entries(out)}
        update_manifest(
            out, lambda m: recordings_manifest(m, out, add_pending=[j.pending() for j in jobs])
        )
        if executor is None:
            built, skipped, failed = _build_here(jobs, out, cfg, progress, overwrite=overwrite)
        else:
            built, skipped, failed = _build_tasks(jobs, out, cfg, executor, before, overwrite)
        manifest = read_manifest(out)
    return BuildSummary(
        out_dir=out,
        built=built,
        skipped=skipped,
        entries=list(manifest["sequences"]),
        complete=bool(manifest.get("complete", True)),
        failed=failed,
    )


def _names(paths: Sequence[str | Path], names: Sequence[str | None] | None) -> list[str | None]:
    """The name of every recording (None: from the recording).

    Raises:
        ConfigError: Not one name per recording.
    """
    names = list(names) if names is not None else [None] * len(paths)
    if len(names) != len(paths):
        raise ConfigError(f"{len(paths)} recordings but {len(names)} names")
    return names


def _jobs(
    paths: Sequence[str | Path],
    names: list[str | None],
    cfg: DatasetConfig,
    topics: dict[str, str],
    reference: str | None,
    initial_guess: InitialGuess | None,
    max_scans: int | None,
) -> list[RecordingJob]:
    """The job of every recording (its content digest and option fingerprints)."""
    return [
        recording_job(
            p,
            cfg,
            reference=reference,
            name=n,
            initial_guess=initial_guess,
            max_scans=max_scans,
            topics=topics,
        )
        for p, n in zip(paths, names, strict=True)
    ]


def _topics(
    scan_topic: str | None, odom_topic: str | None, reference_topic: str | None
) -> dict[str, str]:
    """The topics that were given, by option name."""
    return {
        k: v
        for k, v in (
            ("scan_topic", scan_topic),
            ("odom_topic", odom_topic),
            ("reference_topic", reference_topic),
        )
        if v is not None
    }


#: Sequences built, sequences skipped (resumed), failed recordings with their error.
_Outcomes = tuple[list[str], list[str], dict[str, str]]


def _build_here(
    jobs: list[RecordingJob], out: Path, cfg: DatasetConfig, progress: bool, *, overwrite: bool
) -> _Outcomes:
    """Build the recordings one after the other in this process (the first failure raised)."""
    built: list[str] = []
    skipped: list[str] = []
    for job in jobs:
        try:
            seq_name, was_built = build_recording(
                job, out, cfg, progress=progress, overwrite=overwrite
            )
        except ScanGuardError:
            # it cannot succeed as asked: not pending any more (the error says why)
            drop_pending(out, job)
            raise
        (built if was_built else skipped).append(seq_name)
    return built, skipped, {}


def _build_tasks(
    jobs: list[RecordingJob],
    out: Path,
    cfg: DatasetConfig,
    executor: Executor,
    before: set[str],
    overwrite: bool,
) -> _Outcomes:
    """Build the recordings as tasks of ``executor`` (a failure costs only its recording).

    ``before``: the sequences of the manifest before this build (their order is kept).
    """
    built: list[str] = []
    skipped: list[str] = []
    failed: dict[str, str] = {}
    tasks = [RecordingTask(job, out, cfg, overwrite) for job in jobs]
    for task, outcome in executor.map(recording_task, tasks):
        job = task.job
        value = outcome.value if outcome.ok else None
        if value is None or "error" in value:
            error = value["error"] if value is not None else str(outcome.error)
            failed[str(job.path)] = error
            log.error("%s: failed: %s", job.path, error)
            if value is not None:  # a ScanGuardError: a rerun cannot fix it
                drop_pending(out, job)
            continue
        (built if value["built"] else skipped).append(str(value["sequence"]))
    order = {name: k for k, name in enumerate(built)}
    # new entries were appended as tasks finished: put them in the order of ``paths``
    update_manifest(out, lambda m: order_new_entries(m, before, order))
    return built, skipped, failed


def build_from_recording(
    path: str | Path,
    out_dir: str | Path,
    config: DatasetConfig | None = None,
    *,
    reference: str | None = None,
    name: str | None = None,
    initial_guess: InitialGuess | None = None,
    max_scans: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    reference_topic: str | None = None,
) -> BuildSummary:
    """Label every consecutive pair of a recording with a reference; add it to a build dir.

    The environment and sequence name is the recording's name (or ``<name>_<hash>`` when a
    different recording already has it); the split is ``"heldout"``. Several recordings can
    be added to the same directory (the manifest accumulates); see `build_from_recordings`
    for identity, resuming and locking.

    Args:
        path: Recording readable by `scanguard.io.read_sequence`.
        out_dir: Build directory.
        config: Matcher, labels, odometry noise (environments are ignored).
        reference: TUM file or ``"static"`` (passed to ``read_sequence``).
        name: Override the environment/sequence name.
        initial_guess: Override ``config.recording_initial_guess``.
        max_scans: Use only the first scans (quick looks, tests).
        progress: Show a progress bar.
        overwrite: Replace an existing file of this recording built with other settings.
        scan_topic: LaserScan topic (CARMEN: laser message type).
        odom_topic: Odometry topic.
        reference_topic: Reference pose topic.

    Returns:
        A `BuildSummary` of the whole directory.

    Raises:
        InputError: The recording is missing, unreadable or has no reference.
        ConfigError: The recording was built here with other settings (not ``overwrite``).
    """
    return build_from_recordings(
        [path],
        out_dir,
        config,
        reference=reference,
        initial_guess=initial_guess,
        max_scans=max_scans,
        progress=progress,
        overwrite=overwrite,
        names=[name],
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
    )
