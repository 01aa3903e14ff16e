"""Build labelled pair datasets: match every consecutive pair, compare with the reference, store.

A build directory holds ``sequences/<sequence>.h5`` (one file per sequence, each written
atomically), ``manifest.json`` (rewritten atomically after every finished sequence) and the
resolved ``config.yaml``. Every sequence depends only on the config and its own seed, so an
interrupted build resumes by skipping the files that already exist and ends with exactly the
data an uninterrupted build would have written.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from scanguard.config import save_config
from scanguard.dataset.config import DatasetConfig, EnvironmentSpec, InitialGuess, OdometryNoise
from scanguard.dataset.store import (
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    SEQUENCE_DIR,
    SequenceRecords,
    read_manifest,
    scans_to_arrays,
    write_manifest,
    write_sequence_file,
)
from scanguard.errors import ConfigError, InputError
from scanguard.geometry import compose, relative
from scanguard.labels import LabelConfig, assign_labels, pair_errors
from scanguard.scan import ScanSequence

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
    d = np.hypot(steps[:, 0], steps[:, 1])
    s_xy = noise.trans_floor + noise.trans_per_m * d
    s_th = (
        math.radians(noise.rot_floor_deg)
        + noise.rot_per_rad * np.abs(steps[:, 2])
        + math.radians(noise.rot_per_m_deg) * d
    )
    z = rng.standard_normal((steps.shape[0], 3))
    eps = np.stack([z[:, 0] * s_xy, z[:, 1] * s_xy, z[:, 2] * s_th], axis=-1)
    return compose(steps, eps)


def resolve_initial_guess(seq: ScanSequence, mode: InitialGuess) -> InitialGuess:
    """Turn ``"auto"`` into a concrete initial-guess mode for a recording.

    Recorded odometry is used when present, except for corrected logs (their odometry is not
    aligned with the scans); corrected logs get odometry simulated from the reference;
    anything else starts from identity.
    """
    if mode != "auto":
        return mode
    if seq.reference_kind == "corrected_log":
        return "simulated_odometry"
    if seq.odometry is not None:
        return "odometry"
    return "identity"


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
        gmapping: Also compute `scanguard.baselines.gmapping_score` per pair.
        meta: Extra provenance stored as JSON.
        on_pair: Progress callback.

    Returns:
        The records, ready for `write_sequence_file`.

    Raises:
        InputError: The sequence has no reference or fewer than two scans.
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
    gm_score: Callable[..., float] | None = None
    if gmapping:
        from scanguard.baselines import gmapping_score

        gm_score = gmapping_score
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
        row = dict(res.metrics())
        if gm_score is not None:
            row["gmapping_score"] = float(gm_score(seq.scans[k], seq.scans[k + 1], pose))
        metric_rows.append(row)
        if on_pair is not None:
            on_pair(1)
    names = sorted({key for row in metric_rows for key in row})
    metrics = {
        key: np.array([row.get(key, np.nan) for row in metric_rows], dtype=np.float64)
        for key in names
    }
    lab = assign_labels(errs[:, 0], errs[:, 1], errs[:, 2], labels)
    arrays = scans_to_arrays(seq.scans)
    full_meta: dict[str, Any] = {
        "labels": labels.model_dump(mode="json"),
        "matcher": matcher_name,
        "initial_guess": mode,
        "odometry_noise": noise.model_dump(mode="json") if mode == "simulated_odometry" else None,
        "source": _jsonable(seq.metadata),
        "sensor": _jsonable(seq.sensor.__dict__ if seq.sensor is not None else None),
    }
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


def _file_fingerprint(path: Path) -> str | None:
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                return None
            return str(f.attrs.get("config_fingerprint", ""))
    except OSError:
        return None


def _entry(rec: SequenceRecords, file: str) -> dict[str, Any]:
    return {
        "file": file,
        "environment": rec.environment,
        "sequence": rec.sequence,
        "split": rec.split,
        "pairs": rec.n_pairs,
        **rec.counts(),
    }


def _entry_from_file(path: Path, file: str) -> dict[str, Any]:
    with h5py.File(path, "r") as f:
        lab = f["pairs/label"][()]
        return {
            "file": file,
            "environment": str(f.attrs["environment"]),
            "sequence": str(f.attrs["sequence"]),
            "split": str(f.attrs["split"]),
            "pairs": int(lab.size),
            "normal": int((lab == 0).sum()),
            "fault": int((lab == 1).sum()),
            "ambiguous": int((lab == -1).sum()),
        }


def _simulate(item: PlannedSequence) -> ScanSequence:
    from scanguard.sim import simulate

    env = item.environment
    seq = simulate(env.scenario, seed=item.seed, duration=env.duration, **env.overrides)
    if env.scan_stride > 1:
        seq = seq.subsequence(slice(None, None, env.scan_stride))
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
        },
        on_pair=on_pair,
    )
    rec.attrs["config_fingerprint"] = fingerprint
    write_sequence_file(out / item.file, rec)
    return _entry(rec, item.file)


@contextlib.contextmanager
def _progress(enabled: bool, total: int, what: str) -> Iterator[Callable[[int], None]]:
    if not enabled:
        yield lambda n: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    ) as bar:
        task = bar.add_task(what, total=total)
        yield lambda n: bar.advance(task, n)


@dataclass
class BuildSummary:
    """What a build did.

    Attributes:
        out_dir: The build directory.
        built: Sequences built in this run.
        skipped: Sequences already present (resumed).
        entries: Manifest entries of all sequences, in plan order.
    """

    out_dir: Path
    built: list[str]
    skipped: list[str]
    entries: list[dict[str, Any]]

    def totals(self) -> dict[str, int]:
        """Summed pair counts."""
        keys = ("pairs", "normal", "fault", "ambiguous")
        return {k: sum(int(e[k]) for e in self.entries) for k in keys}


def _manifest(config: DatasetConfig, entries: list[dict[str, Any]], complete: bool) -> dict:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": config.name,
        "config_fingerprint": config.fingerprint(),
        "matcher": config.matcher,
        "initial_guess": config.initial_guess,
        "labels": config.labels.model_dump(mode="json"),
        "complete": complete,
        "sequences": entries,
    }


def build_dataset(
    config: DatasetConfig,
    out_dir: str | Path,
    *,
    progress: bool = True,
    overwrite: bool = False,
    max_sequences: int | None = None,
    workers: int = 1,
) -> BuildSummary:
    """Simulate, match, label and store every sequence of ``config`` (resumable).

    Args:
        config: The build.
        out_dir: Build directory (created).
        progress: Show a progress bar.
        overwrite: Rebuild sequence files made with a different config instead of failing.
        max_sequences: Stop after building this many new sequences (for tests of resuming).
        workers: Processes building sequences in parallel (1 = in this process).

    Returns:
        A `BuildSummary`.

    Raises:
        ConfigError: An existing sequence file was built with another config (and not
            ``overwrite``), or the config has no environments.
    """
    if not config.environments:
        raise ConfigError(f"dataset config {config.name!r} has no environments to simulate")
    out = Path(out_dir)
    (out / SEQUENCE_DIR).mkdir(parents=True, exist_ok=True)
    fp = config.fingerprint()
    save_config(config, out)
    plan = plan_build(config)
    done: dict[str, dict[str, Any]] = {}
    todo: list[PlannedSequence] = []
    for item in plan:
        path = out / item.file
        if path.exists():
            got = _file_fingerprint(path)
            if got == fp:
                done[item.sequence] = _entry_from_file(path, item.file)
                continue
            if not overwrite:
                raise ConfigError(
                    f"{path}: built with another config (fingerprint {got}, now {fp}); "
                    "use another output directory or --overwrite"
                )
        todo.append(item)
    if max_sequences is not None:
        todo = todo[:max_sequences]
    skipped = list(done)
    log.info("%s: %d sequences to build, %d already done", out, len(todo), len(skipped))

    def entries() -> list[dict[str, Any]]:
        return [done[p.sequence] for p in plan if p.sequence in done]

    built: list[str] = []
    total_pairs = sum(_expected_pairs(p) for p in todo)
    with _progress(progress, total_pairs, f"dataset {config.name}") as advance:
        if workers <= 1 or len(todo) <= 1:
            for item in todo:
                done[item.sequence] = _build_one(item, config, fp, out, advance)
                built.append(item.sequence)
                write_manifest(out, _manifest(config, entries(), len(done) == len(plan)))
        else:
            from concurrent.futures import ProcessPoolExecutor, as_completed

            with ProcessPoolExecutor(max_workers=workers) as pool:
                futs = {pool.submit(_build_one, it, config, fp, out): it for it in todo}
                for fut in as_completed(futs):
                    item = futs[fut]
                    done[item.sequence] = fut.result()
                    built.append(item.sequence)
                    advance(_expected_pairs(item))
                    write_manifest(out, _manifest(config, entries(), len(done) == len(plan)))
    write_manifest(out, _manifest(config, entries(), len(done) == len(plan)))
    return BuildSummary(out_dir=out, built=built, skipped=skipped, entries=entries())


def _expected_pairs(item: PlannedSequence) -> int:
    # the progress total only; the simulator's exact scan count may differ by one
    env = item.environment
    stride = int(env.overrides.get("stride", 1)) * env.scan_stride
    return max(1, int(env.duration * 10.0 / stride))


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
) -> BuildSummary:
    """Label every consecutive pair of a recording with a reference; add it to a build dir.

    The environment and sequence name is the recording's name; the split is ``"heldout"``.
    Several recordings can be added to the same directory (the manifest accumulates).

    Args:
        path: Recording readable by `scanguard.io.read_sequence`.
        out_dir: Build directory.
        config: Matcher, labels, odometry noise (environments are ignored).
        reference: TUM file or ``"static"`` (passed to ``read_sequence``).
        name: Override the environment/sequence name.
        initial_guess: Override ``config.recording_initial_guess``.
        max_scans: Use only the first scans (quick looks, tests).
        progress: Show a progress bar.
        overwrite: Replace an existing file of this recording built with another config.

    Returns:
        A `BuildSummary` of the whole directory.

    Raises:
        InputError: The recording has no reference.
    """
    from scanguard.io import read_sequence

    cfg = config or DatasetConfig()
    mode = initial_guess or cfg.recording_initial_guess
    seq = read_sequence(path, reference=reference)
    if seq.reference is None:
        raise InputError(
            path, "recording has no reference poses; pass --reference TUM or --reference static"
        )
    if max_scans is not None:
        seq = seq.subsequence(slice(0, max_scans))
    seq_name = _safe_name(name or seq.name)
    out = Path(out_dir)
    (out / SEQUENCE_DIR).mkdir(parents=True, exist_ok=True)
    rel = f"{SEQUENCE_DIR}/{seq_name}.h5"
    fp_src = {
        "matcher": cfg.matcher,
        "labels": cfg.labels.model_dump(mode="json"),
        "odometry_noise": cfg.odometry_noise.model_dump(mode="json"),
        "gmapping_score": cfg.gmapping_score,
        "initial_guess": mode,
        "reference": reference,
        "max_scans": max_scans,
        "recording": Path(path).name,
    }
    import hashlib

    fp = hashlib.sha256(json.dumps(fp_src, sort_keys=True).encode()).hexdigest()[:16]
    manifest: dict[str, Any] = {"format": FORMAT, "format_version": FORMAT_VERSION}
    if (out / MANIFEST).exists():
        manifest = read_manifest(out)
    entries = {e["sequence"]: e for e in manifest.get("sequences", [])}
    target = out / rel
    built, skipped = [], []
    if target.exists() and _file_fingerprint(target) == fp:
        skipped.append(seq_name)
        entries[seq_name] = _entry_from_file(target, rel)
    else:
        if target.exists() and not overwrite:
            raise ConfigError(
                f"{target}: built with other settings; use another output directory or --overwrite"
            )
        with _progress(progress, len(seq) - 1, f"recording {seq_name}") as advance:
            rec = label_sequence(
                seq,
                environment=seq_name,
                sequence=seq_name,
                split="heldout",
                matcher=_matcher(cfg.matcher),
                matcher_name=cfg.matcher,
                initial_guess=mode,
                labels=cfg.labels,
                odometry_noise=cfg.odometry_noise,
                gmapping=cfg.gmapping_score,
                meta={"recording": str(path), "reference_arg": reference},
                on_pair=advance,
            )
        rec.attrs["config_fingerprint"] = fp
        write_sequence_file(target, rec)
        entries[seq_name] = _entry(rec, rel)
        built.append(seq_name)
    ordered = [entries[k] for k in sorted(entries)]
    manifest.update(
        {
            "name": manifest.get("name", out.name),
            "kind": "recordings",
            "complete": True,
            "sequences": ordered,
        }
    )
    write_manifest(out, manifest)
    return BuildSummary(out_dir=out, built=built, skipped=skipped, entries=ordered)


def _safe_name(name: str) -> str:
    keep = [c if (c.isalnum() or c in "-_.") else "_" for c in name]
    return "".join(keep).strip("._") or "recording"
