"""Build labelled pair datasets: match every consecutive pair, compare with the reference, store.

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

import contextlib
import functools
import hashlib
import json
import logging
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np
from numpy.typing import NDArray

from scanguard.config import save_config
from scanguard.dataset.config import DatasetConfig, EnvironmentSpec, InitialGuess
from scanguard.dataset.manifest import build_session, update_manifest
from scanguard.dataset.randomize import draw_domain, randomized_sequence, simulated_duration
from scanguard.dataset.store import (
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    SEQUENCE_DIR,
    SequenceRecords,
    read_manifest,
    scans_to_arrays,
    write_sequence_file,
)
from scanguard.errors import ConfigError, InputError, ScanGuardError
from scanguard.geometry import compose, relative
from scanguard.pairs.features import pair_metrics
from scanguard.pairs.labels import (
    AMBIGUOUS,
    FAULT,
    NORMAL,
    LabelConfig,
    assign_labels,
    non_finite_errors,
    pair_errors,
)
from scanguard.pairs.odometry import OdometryNoise, odometry_sigmas
from scanguard.scan import ScanSequence

if TYPE_CHECKING:
    from scanguard.runtime.executor import Executor

log = logging.getLogger(__name__)

#: Called after each pair with the number of pairs just done (for progress bars).
PairCallback = Callable[[int], None]


def _name_seed(name: str, seed: int) -> int:
    # crc32 is stable across runs and platforms, unlike hash()
    return (zlib.crc32(name.encode()) + 7919 * seed) & 0x7FFFFFFF


def simulated_odometry_steps(
    reference_steps: NDArray[np.float64], noise: OdometryNoise, name: str
) -> NDArray[np.float64]:
    """Noisy relative motions from exact ones (odometry simulated from reference poses).

    Args:
        reference_steps: ``(P, 3)`` exact relative motions between consecutive scans.
        noise: Noise model (see `OdometryNoise`).
        name: Sequence name; seeds the noise together with ``noise.seed``.

    Returns:
        ``(P, 3)`` noisy relative motions ``step ⊕ noise``.
    """
    steps = np.asarray(reference_steps, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(_name_seed(name, noise.seed))
    s_xy, s_th = odometry_sigmas(steps, noise)
    z = rng.standard_normal((steps.shape[0], 3))
    eps = np.stack([z[:, 0] * s_xy, z[:, 1] * s_xy, z[:, 2] * s_th], axis=-1)
    return compose(steps, eps)


def resolve_initial_guess(seq: ScanSequence, mode: InitialGuess) -> InitialGuess:
    """Turn ``"auto"`` into a concrete initial-guess mode for a recording.

    One labelling policy serves ``run`` and ``dataset build``: ``"auto"`` gives the matcher
    what the online guard gives it by default (`scanguard.slam.guard.GuardConfig`:
    ``odometry_initial_guess`` off, the paper's identity start), so a recording's dataset
    labels are the labels of the very matches ``run`` judges. A run with
    ``odometry_initial_guess`` on corresponds to ``"odometry"``; ``"simulated_odometry"``
    (the reference motion plus noise) matches no run and is never chosen automatically.
    """
    del seq  # the policy does not depend on the recording (it used to, and labels differed)
    return "identity" if mode == "auto" else mode


def initial_guesses(
    seq: ScanSequence, mode: InitialGuess, noise: OdometryNoise
) -> NDArray[np.float64]:
    """``(N-1, 3)`` initial guesses of the matcher for every consecutive pair.

    Raises:
        InputError: ``"odometry"`` without odometry, or simulated odometry without reference.
    """
    n = len(seq)
    lo = seq.laser_offset
    mode = resolve_initial_guess(seq, mode)
    if mode == "identity":
        return np.zeros((max(n - 1, 0), 3))
    if mode == "odometry":
        if seq.odometry is None:
            raise InputError(None, f"sequence {seq.name!r} has no odometry for the initial guess")
        s = compose(seq.odometry, lo)
        return relative(s[:-1], s[1:])
    if seq.reference is None:
        raise InputError(None, f"sequence {seq.name!r} has no reference to simulate odometry")
    s = compose(seq.reference, lo)
    return simulated_odometry_steps(relative(s[:-1], s[1:]), noise, seq.name)


def label_sequence(
    seq: ScanSequence,
    *,
    environment: str,
    sequence: str,
    split: str,
    matcher: Callable[..., Any],
    matcher_name: str,
    initial_guess: InitialGuess,
    labels: LabelConfig,
    odometry_noise: OdometryNoise | None = None,
    gmapping: bool = True,
    meta: dict[str, Any] | None = None,
    on_pair: PairCallback | None = None,
) -> SequenceRecords:
    """Match every consecutive pair of a sequence and label it against the reference.

    Args:
        seq: Scans with ``reference`` poses (robot frame; ``laser_offset`` is applied).
        environment: Environment name to store.
        sequence: Sequence id to store (unique in a store).
        split: Split name to store.
        matcher: ``matcher(source_points, target_points, initial) -> MatchResult``.
        matcher_name: Name recorded in the metadata.
        initial_guess: Initial-guess mode (``"auto"`` is resolved from the sequence).
        labels: Thresholds.
        odometry_noise: Noise of simulated odometry (default `OdometryNoise()`).
        gmapping: Also compute `scanguard.matching.quality.gmapping_score` per pair.
        meta: Extra provenance stored as JSON.
        on_pair: Progress callback.

    Returns:
        The records, ready for `write_sequence_file`.

    Pairs whose errors are not finite (a NaN reference pose, say) are labelled ambiguous,
    counted in a warning and in ``meta["non_finite_pairs"]``; they are never faults.

    Raises:
        InputError: The sequence has no reference, fewer than two scans, or no pair with a
            finite error.
    """
    if seq.reference is None:
        raise InputError(None, f"sequence {seq.name!r} has no reference poses: cannot label")
    if len(seq) < 2:
        raise InputError(None, f"sequence {seq.name!r} has fewer than two scans")
    noise = odometry_noise or OdometryNoise()
    mode = resolve_initial_guess(seq, initial_guess)
    init = initial_guesses(seq, mode, noise)
    sensor_poses = compose(seq.reference, seq.laser_offset)
    ref_rel = relative(sensor_poses[:-1], sensor_poses[1:])
    points = [s.points(np.float64) for s in seq.scans]
    n_pairs = len(seq) - 1
    est = np.zeros((n_pairs, 3))
    errs = np.zeros((n_pairs, 3))
    iters = np.zeros(n_pairs, dtype=np.int32)
    conv = np.zeros(n_pairs, dtype=bool)
    metric_rows: list[dict[str, float]] = []
    for k in range(n_pairs):
        prev, curr = points[k], points[k + 1]
        res = matcher(curr, prev, init[k])
        pose = np.asarray(res.pose, dtype=np.float64)
        est[k] = pose
        errs[k] = pair_errors(pose, ref_rel[k], curr)
        iters[k] = int(res.iterations)
        conv[k] = bool(res.converged)
        metric_rows.append(pair_metrics(seq.scans[k], seq.scans[k + 1], res, gmapping=gmapping))
        if on_pair is not None:
            on_pair(1)
    names = sorted({key for row in metric_rows for key in row})
    metrics = {
        key: np.array([row.get(key, np.nan) for row in metric_rows], dtype=np.float64)
        for key in names
    }
    lab = assign_labels(errs[:, 0], errs[:, 1], errs[:, 2], labels)
    n_bad = int(non_finite_errors(errs[:, 0], errs[:, 1], errs[:, 2]).sum())
    if n_bad == n_pairs:
        raise InputError(
            None,
            f"sequence {seq.name!r}: no pair has a finite error against the reference "
            "(non-finite reference poses?); nothing to label",
        )
    if n_bad:
        log.warning(
            "sequence %r: %d of %d pairs have non-finite errors (non-finite reference or "
            "estimate); stored as ambiguous, never as faults",
            seq.name,
            n_bad,
            n_pairs,
        )
    arrays = scans_to_arrays(seq.scans)
    full_meta: dict[str, Any] = {
        "labels": labels.model_dump(mode="json"),
        "matcher": matcher_name,
        "initial_guess": mode,
        "odometry_noise": noise.model_dump(mode="json") if mode == "simulated_odometry" else None,
        "source": _jsonable(seq.metadata),
        "sensor": _jsonable(seq.sensor.__dict__ if seq.sensor is not None else None),
    }
    if n_bad:
        full_meta["non_finite_pairs"] = n_bad
    full_meta.update(meta or {})
    return SequenceRecords(
        environment=environment,
        sequence=sequence,
        split=split,
        ranges=arrays["ranges"],
        n_beams=arrays["n_beams"],
        angle_min=arrays["angle_min"],
        angle_increment=arrays["angle_increment"],
        range_min=arrays["range_min"],
        range_max=arrays["range_max"],
        stamps=arrays["stamps"],
        reference=np.asarray(seq.reference, dtype=np.float64),
        odometry=None if seq.odometry is None else np.asarray(seq.odometry, dtype=np.float64),
        laser_offset=seq.laser_offset,
        pairs={
            "prev": np.arange(n_pairs, dtype=np.int32),
            "curr": np.arange(1, n_pairs + 1, dtype=np.int32),
            "estimate": est,
            "initial": np.asarray(init, dtype=np.float64),
            "reference": ref_rel,
            "trans_error": errs[:, 0].copy(),
            "rot_error": errs[:, 1].copy(),
            "disp_error": errs[:, 2].copy(),
            "label": lab,
            "iterations": iters,
            "converged": conv,
        },
        metrics=metrics,
        attrs={
            "reference_kind": str(seq.reference_kind or "unknown"),
            "initial_guess": str(mode),
            "matcher": matcher_name,
            "name": seq.name,
        },
        meta=full_meta,
    )


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj, default=str, sort_keys=True))


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
        return f"{SEQUENCE_DIR}/{self.sequence}.h5"


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
            order = np.random.default_rng(_name_seed(env.name, sp.seed)).permutation(env.sequences)
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


@dataclass
class _FileState:
    """What an existing pair file holds (`_inspect`)."""

    ok: bool
    fingerprint: str | None = None
    entry: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    problem: str = ""


def _inspect(path: Path, file: str) -> _FileState:
    """Open an existing pair file: its fingerprint and manifest entry, or why it is corrupt."""
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if fmt != FORMAT:
                return _FileState(False, problem=f"not a scanguard pair file (format {fmt!r})")
            lab = np.asarray(f["pairs/label"][()])
            if lab.ndim != 1 or f["pairs/curr"].shape[0] != lab.size or "ranges" not in f["scans"]:
                return _FileState(False, problem="inconsistent pair columns")
            entry = {
                "file": file,
                "environment": str(f.attrs["environment"]),
                "sequence": str(f.attrs["sequence"]),
                "split": str(f.attrs["split"]),
                "pairs": int(lab.size),
                "normal": int((lab == NORMAL).sum()),
                "fault": int((lab == FAULT).sum()),
                "ambiguous": int((lab == AMBIGUOUS).sum()),
            }
            meta = json.loads(str(f.attrs.get("meta_json", "{}")))
            fp = f.attrs.get("config_fingerprint")
            return _FileState(
                True,
                fingerprint=None if fp is None else str(fp),
                entry=entry,
                meta=meta if isinstance(meta, dict) else {},
            )
    except (OSError, KeyError, ValueError, TypeError, AttributeError) as exc:
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return _FileState(False, problem=f"unreadable: {detail}")


def _warn_corrupt(path: Path, state: _FileState) -> None:
    log.warning("%s: CORRUPT pair file (%s); rebuilding it", path, state.problem)


def _entry(rec: SequenceRecords, file: str) -> dict[str, Any]:
    return {
        "file": file,
        "environment": rec.environment,
        "sequence": rec.sequence,
        "split": rec.split,
        "pairs": rec.n_pairs,
        **rec.counts(),
    }


def _simulate(item: PlannedSequence) -> ScanSequence:
    """Simulate a planned sequence; with ``randomize``, in its drawn domain.

    A randomised sequence carries its draw (and the resulting scan and pair counts) in
    ``metadata["domain"]``, which `_build_one` stores in the file's meta.
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


def _build_one(
    item: PlannedSequence,
    config: DatasetConfig,
    fingerprint: str,
    out: Path,
    on_pair: PairCallback | None = None,
) -> dict[str, Any]:
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
            "overrides": _jsonable(item.environment.overrides),
            # only randomised sequences have it (older files' meta stays as it was)
            **({"domain": _jsonable(seq.metadata["domain"])} if "domain" in seq.metadata else {}),
        },
        on_pair=on_pair,
    )
    rec.attrs["config_fingerprint"] = fingerprint
    write_sequence_file(out / item.file, rec)
    return _entry(rec, item.file)


@contextlib.contextmanager
def _progress(enabled: bool, total: int, what: str) -> Iterator[Callable[[int], None]]:
    # a bar on a terminal, log lines otherwise (a bar must never fill a log file)
    from scanguard.logging_utils import progress

    with progress(total, what, enabled=enabled) as advance:
        yield lambda n: advance(n)


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


def _manifest(
    config: DatasetConfig, entries: list[dict[str, Any]], pending: list[dict[str, Any]]
) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": config.name,
        "config_fingerprint": config.fingerprint(),
        "matcher": config.matcher,
        "initial_guess": config.initial_guess,
        "labels": config.labels.model_dump(mode="json"),
        "complete": not pending,
        "pending": pending,
        "sequences": entries,
    }


def _is_recording_entry(out: Path, entry: dict[str, Any]) -> bool:
    """An entry added by a ``--recording`` build (older ones are known by their metadata)."""
    if "recording" in entry:
        return True
    state = _inspect(out / entry["file"], entry["file"])
    return state.ok and "recording" in state.meta


def _simulated_manifest(
    current: dict[str, Any],
    out: Path,
    config: DatasetConfig,
    plan: list[PlannedSequence],
    done: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """The manifest after a step of a simulated build, keeping what other builds added.

    Entries of recordings (and anything else not in the plan whose file exists) are kept
    after the planned sequences; when the directory held another simulated config (rebuilt
    with ``overwrite``) its sequences that are not in the new plan are dropped. Work pending
    in other builds (recordings) stays pending.
    """
    planned = {p.sequence for p in plan}
    replaced = current.get("config_fingerprint") not in (None, config.fingerprint())
    others = []
    for e in current.get("sequences", []):
        if e.get("sequence") in planned:
            continue
        if replaced and not _is_recording_entry(out, e):
            continue
        if not (out / e["file"]).is_file():
            log.warning("%s: listed in the manifest but missing; dropped", out / e["file"])
            continue
        others.append(e)
    # work other builds registered (recordings, merged sources) stays pending
    pending = [x for x in current.get("pending", []) if "recording" in x or "source" in x]
    pending += [{"sequence": p.sequence} for p in plan if p.sequence not in done]
    entries = [done[p.sequence] for p in plan if p.sequence in done] + others
    new = dict(current)
    new.update(_manifest(config, entries, pending))
    new["kind"] = "mixed" if others else "simulated"
    return new


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
        executor: Where the sequences are built, one task each (`scanguard.scale`: a local
            process pool or Ray). A failing task costs only its sequence: it is listed in
            ``BuildSummary.failed``, stays pending in the manifest, and a rerun builds it.

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
                state = _inspect(path, item.file)
                if not state.ok:
                    _warn_corrupt(path, state)
                elif state.fingerprint == fp and state.entry is not None:
                    done[item.sequence] = state.entry
                    continue
                elif not overwrite:
                    raise ConfigError(
                        f"{path}: built with another config (fingerprint {state.fingerprint}, "
                        f"now {fp}); use another output directory or --overwrite"
                    )
            todo.append(item)
        # only now: a refused build must leave the config of the data in place
        save_config(config, out)
        if max_sequences is not None:
            todo = todo[:max_sequences]
        skipped = list(done)
        log.info("%s: %d sequences to build, %d already done", out, len(todo), len(skipped))

        def record() -> dict[str, Any]:
            return update_manifest(
                out, lambda current: _simulated_manifest(current, out, config, plan, done)
            )

        manifest = record()
        built: list[str] = []
        failed: dict[str, str] = {}
        total_pairs = sum(_expected_pairs(p) for p in todo)
        with _progress(progress, total_pairs, f"dataset {config.name}") as advance:
            if executor is None and (workers <= 1 or len(todo) <= 1):
                for item in todo:
                    done[item.sequence] = _build_one(item, config, fp, out, advance)
                    built.append(item.sequence)
                    manifest = record()
            else:
                from scanguard.runtime.executor import LocalExecutor

                pool = executor if executor is not None else LocalExecutor(workers)
                tasks = [_SequenceTask(it, config, fp, out) for it in todo]
                for task, outcome in pool.map(_build_task, tasks):
                    item = task.item
                    advance(_expected_pairs(item))
                    if not outcome.ok or outcome.value is None:
                        # its shard only: the others go on, a rerun builds it (still pending)
                        failed[item.sequence] = outcome.error or "no result"
                        log.error("%s: failed: %s", item.sequence, failed[item.sequence])
                        continue
                    done[item.sequence] = outcome.value
                    built.append(item.sequence)
                    manifest = record()
        manifest = record()
    return BuildSummary(
        out_dir=out,
        built=built,
        skipped=skipped,
        entries=list(manifest["sequences"]),
        complete=bool(manifest["complete"]),
        failed=failed,
    )


@dataclass(frozen=True)
class _SequenceTask:
    """One sequence of a simulated build, sent to a worker (picklable)."""

    item: PlannedSequence
    config: DatasetConfig
    fingerprint: str
    out: Path


def _build_task(task: _SequenceTask) -> dict[str, Any]:
    """Build one planned sequence into its own shard (top-level: spawn- and Ray-safe)."""
    return _build_one(task.item, task.config, task.fingerprint, task.out)


def _expected_pairs(item: PlannedSequence) -> int:
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
        InputError: The recording is missing or unreadable.
    """
    p = Path(path)
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
class _RecordingJob:
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


def _recording_job(
    path: str | Path,
    cfg: DatasetConfig,
    *,
    reference: str | None,
    name: str | None,
    initial_guess: InitialGuess | None,
    max_scans: int | None,
    topics: dict[str, str],
) -> _RecordingJob:
    p = Path(path)
    mode = initial_guess or cfg.recording_initial_guess
    ref_digest = None
    if reference is not None and str(reference).lower() != "static" and Path(reference).is_file():
        ref_digest = recording_digest(reference)
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
    return _RecordingJob(
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


def _recordings_manifest(
    current: dict[str, Any],
    out: Path,
    *,
    add_pending: Sequence[dict[str, Any]] = (),
    drop_pending: str | None = None,
    entry: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The manifest after a step of a recording build (under the manifest lock).

    Args:
        current: The manifest on disk.
        out: Build directory.
        add_pending: Pending items to (re)register; older items of the same fingerprint
            are replaced.
        drop_pending: Remove the pending item with this fingerprint (the recording is done
            or failed for good).
        entry: Put this entry in place of the entry of the same sequence (or append it).
    """
    new = dict(current)
    fps = {x["fingerprint"] for x in add_pending}
    if drop_pending is not None:
        fps.add(drop_pending)
    pending = [x for x in current.get("pending", []) if x.get("fingerprint") not in fps]
    pending += list(add_pending)
    entries = list(current.get("sequences", []))
    if entry is not None:
        at = [i for i, e in enumerate(entries) if e.get("sequence") == entry["sequence"]]
        if at:
            entries[at[0]] = entry
        else:
            entries.append(entry)
    new["sequences"] = entries
    new["pending"] = pending
    new["complete"] = not pending
    new.setdefault("name", out.name)
    new["kind"] = "recordings" if "config_fingerprint" not in current else "mixed"
    return new


def _find_built(
    out: Path, job: _RecordingJob, entries: list[dict[str, Any]], overwrite: bool
) -> str | None:
    """The sequence this recording is already stored as, or None (corrupt files reported).

    A file built before content identity (same file name and options) is kept with a
    warning, unless ``overwrite`` asks to rebuild it.
    """
    for e in entries:
        if e.get("fingerprint") == job.fingerprint:
            path = out / e["file"]
            state = _inspect(path, e["file"])
            if state.ok and state.fingerprint == job.fingerprint:
                return str(e["sequence"])
            if path.exists():
                _warn_corrupt(path, state)
        elif not overwrite and "fingerprint" not in e and e.get("split") == "heldout":
            state = _inspect(out / e["file"], e["file"])
            if state.ok and state.fingerprint == job.legacy:
                log.warning(
                    "%s: built before recordings were identified by content; kept as %s "
                    "without checking that the recording is unchanged (--overwrite rebuilds it)",
                    job.path,
                    e["sequence"],
                )
                return str(e["sequence"])
    return None


def _claim_name(
    current: dict[str, Any], out: Path, job: _RecordingJob, base: str, overwrite: bool
) -> tuple[str, dict[str, Any] | None]:
    """Choose the sequence name of a recording (under the manifest lock).

    The same recording (same resolved path) built from other content is rebuilt under its
    old name (stale pairs replaced); with other options it is refused unless ``overwrite``.
    A different recording with a name already taken gets ``<name>_<first 8 hex of its
    hash>``. An unlisted file of the same identity (a build killed before its manifest
    update) is adopted.

    Returns:
        The name, and the entry of an adopted file (None: build it).

    Raises:
        ConfigError: The recording was built here with other settings (not ``overwrite``).
    """
    entries = current.get("sequences", [])
    for e in entries:
        if e.get("fingerprint") == job.fingerprint:
            return str(e["sequence"]), None  # its file is corrupt (reported): rebuild
    for e in entries:
        if e.get("recording") != job.source:
            continue
        if e.get("options_fingerprint") == job.options:
            log.warning(
                "%s: the recording changed since it was built into %s; rebuilding it (its "
                "stale pairs are replaced)",
                job.path,
                out / e["file"],
            )
        elif not overwrite:
            raise ConfigError(
                f"{out / e['file']}: built from {job.path} with other settings; use another "
                "output directory or --overwrite"
            )
        return str(e["sequence"]), None
    by_seq = {str(e.get("sequence")): e for e in entries}
    reserved = {
        str(x["sequence"])
        for x in current.get("pending", [])
        if "sequence" in x and x.get("fingerprint") != job.fingerprint
    }
    candidates = [base, f"{base}_{job.digest[:8]}", f"{base}_{job.digest[:16]}"]
    for cand in candidates:
        if cand in reserved:
            continue
        rel = f"{SEQUENCE_DIR}/{cand}.h5"
        e = by_seq.get(cand)
        if e is None:
            state = _inspect(out / rel, rel) if (out / rel).exists() else None
            if state is not None and state.ok and state.fingerprint == job.fingerprint:
                assert state.entry is not None
                return cand, {**state.entry, **job.entry_fields()}
            return cand, None  # free, or an orphan of an interrupted build: replaced
        if "recording" in e:
            continue  # another recording's name
        state = _inspect(out / e["file"], e["file"])
        if not state.ok:
            _warn_corrupt(out / e["file"], state)
            return cand, None
        old = state.meta.get("recording")
        if old is not None and Path(str(old)).name == job.path.name:
            # built before content identity from a file of this name: the same recording
            if not overwrite:
                raise ConfigError(
                    f"{out / e['file']}: built with other settings; use another output "
                    "directory or --overwrite"
                )
            return cand, None
    raise ConfigError(
        f"{out}: no free sequence name for {job.path} (tried {', '.join(candidates)})"
    )


def _build_recording(
    job: _RecordingJob, out: Path, cfg: DatasetConfig, *, progress: bool, overwrite: bool
) -> tuple[str, bool]:
    """Build one recording into ``out`` (inside a `build_session`).

    Returns:
        Its sequence name, and whether it was built (False: already there, resumed).
    """
    from scanguard.io import read_sequence

    entries = read_manifest(out)["sequences"] if (out / MANIFEST).exists() else []
    known = _find_built(out, job, entries, overwrite)
    if known is not None:
        update_manifest(out, lambda m: _recordings_manifest(m, out, drop_pending=job.fingerprint))
        log.info("%s: already in %s as %s (resumed)", job.path, out, known)
        return known, False
    seq = read_sequence(
        job.path,
        reference=job.reference,
        scan_topic=job.topics.get("scan_topic"),
        odom_topic=job.topics.get("odom_topic"),
        reference_topic=job.topics.get("reference_topic"),
    )
    if seq.reference is None:
        raise InputError(
            job.path, "recording has no reference poses; pass --reference TUM or --reference static"
        )
    if job.max_scans is not None:
        seq = seq.subsequence(slice(0, job.max_scans))
    base = _safe_name(job.name or seq.name)
    claimed: dict[str, Any] = {}

    def claim(current: dict[str, Any]) -> dict[str, Any]:
        name, adopted = _claim_name(current, out, job, base, overwrite)
        claimed.update(name=name, adopted=adopted)
        if adopted is not None:
            return _recordings_manifest(current, out, drop_pending=job.fingerprint, entry=adopted)
        return _recordings_manifest(current, out, add_pending=[job.pending(name)])

    update_manifest(out, claim)
    seq_name: str = claimed["name"]
    if claimed["adopted"] is not None:
        log.info("%s: found its finished file %s (resumed)", job.path, claimed["adopted"]["file"])
        return seq_name, False
    rel = f"{SEQUENCE_DIR}/{seq_name}.h5"
    with _progress(progress, len(seq) - 1, f"recording {seq_name}") as advance:
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
    write_sequence_file(out / rel, rec)
    entry = {**_entry(rec, rel), **job.entry_fields()}
    update_manifest(
        out, lambda m: _recordings_manifest(m, out, drop_pending=job.fingerprint, entry=entry)
    )
    return seq_name, True


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
        executor: Build the recordings as tasks of this executor (`scanguard.scale`), each
            into its own shard; a recording that fails is reported in
            ``BuildSummary.failed`` and the others finish. None: one after the other in this
            process, the first failure raised.

    Returns:
        A `BuildSummary` of the whole directory; ``built``, ``skipped`` and ``failed`` cover
        every recording of this call (``entries`` in the order of ``paths``).

    Raises:
        InputError: A recording is missing, unreadable or has no reference.
        ConfigError: A recording was built here with other settings (not ``overwrite``).
    """
    cfg = config or DatasetConfig()
    out = Path(out_dir)
    names = list(names) if names is not None else [None] * len(paths)
    if len(names) != len(paths):
        raise ConfigError(f"{len(paths)} recordings but {len(names)} names")
    topics = {
        k: v
        for k, v in (
            ("scan_topic", scan_topic),
            ("odom_topic", odom_topic),
            ("reference_topic", reference_topic),
        )
        if v is not None
    }
    built: list[str] = []
    skipped: list[str] = []
    failed: dict[str, str] = {}
    with build_session(out):
        jobs = [
            _recording_job(
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
        before = {str(e.get("sequence")) for e in _manifest_entries(out)}
        update_manifest(
            out, lambda m: _recordings_manifest(m, out, add_pending=[j.pending() for j in jobs])
        )
        if executor is None:
            for job in jobs:
                try:
                    seq_name, was_built = _build_recording(
                        job, out, cfg, progress=progress, overwrite=overwrite
                    )
                except ScanGuardError:
                    # it cannot succeed as asked: not pending any more (the error says why)
                    _drop_pending(out, job)
                    raise
                (built if was_built else skipped).append(seq_name)
        else:
            tasks = [_RecordingTask(job, out, cfg, overwrite) for job in jobs]
            for task, outcome in executor.map(_recording_task, tasks):
                job = task.job
                value = outcome.value if outcome.ok else None
                if value is None or "error" in value:
                    error = value["error"] if value is not None else str(outcome.error)
                    failed[str(job.path)] = error
                    log.error("%s: failed: %s", job.path, error)
                    if value is not None:  # a ScanGuardError: a rerun cannot fix it
                        _drop_pending(out, job)
                    continue
                (built if value["built"] else skipped).append(str(value["sequence"]))
            order = {name: k for k, name in enumerate(built)}
            # new entries were appended as tasks finished: put them in the order of ``paths``
            update_manifest(out, lambda m: _order_new_entries(m, before, order))
        manifest = read_manifest(out)
    return BuildSummary(
        out_dir=out,
        built=built,
        skipped=skipped,
        entries=list(manifest["sequences"]),
        complete=bool(manifest.get("complete", True)),
        failed=failed,
    )


def _manifest_entries(out: Path) -> list[dict[str, Any]]:
    return list(read_manifest(out)["sequences"]) if (out / MANIFEST).exists() else []


def _drop_pending(out: Path, job: _RecordingJob) -> None:
    update_manifest(
        out, functools.partial(_recordings_manifest, out=out, drop_pending=job.fingerprint)
    )


def _order_new_entries(
    current: dict[str, Any], before: set[str], order: dict[str, int]
) -> dict[str, Any]:
    """The manifest with the entries added since ``before`` sorted by ``order`` (in place)."""
    entries = list(current.get("sequences", []))
    slots = [i for i, e in enumerate(entries) if str(e.get("sequence")) not in before]
    new = sorted(
        (entries[i] for i in slots), key=lambda e: order.get(str(e.get("sequence")), len(order))
    )
    for i, e in zip(slots, new, strict=True):
        entries[i] = e
    return {**current, "sequences": entries}


@dataclass(frozen=True)
class _RecordingTask:
    """One recording of a build, sent to a worker (picklable)."""

    job: _RecordingJob
    out: Path
    config: DatasetConfig
    overwrite: bool


def _recording_task(task: _RecordingTask) -> dict[str, Any]:
    """Build one recording into its own shard (top-level: spawn- and Ray-safe).

    Returns:
        ``{"sequence", "built"}``, or ``{"error"}`` with the one-line message of a
        `ScanGuardError` (a recording that cannot be read or labelled as asked). Anything
        else (a bug, a killed worker) propagates and leaves the recording pending.
    """
    from scanguard.runtime.executor import error_line

    try:
        name, was_built = _build_recording(
            task.job, task.out, task.config, progress=False, overwrite=task.overwrite
        )
    except ScanGuardError as exc:
        return {"error": error_line(exc)}
    return {"sequence": name, "built": was_built}


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


def _safe_name(name: str) -> str:
    keep = [c if (c.isalnum() or c in "-_.") else "_" for c in name]
    return "".join(keep).strip("._") or "recording"
