"""Labelling: match every consecutive pair of a sequence and label it against the reference.

One labelling policy serves ``run`` and ``dataset build`` (`resolve_initial_guess`): the
matcher gets the initial guess the online guard gives it, so a recording's dataset labels
are the labels of the very matches ``run`` judges. `simulated_odometry_steps` draws the
noisy odometry of sequences that have none (seeded per sequence name).
"""

from __future__ import annotations

import json
import logging
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.dataset.config import InitialGuess
from scanguard.dataset.shards import SequenceRecords, scans_to_arrays
from scanguard.errors import InputError
from scanguard.geometry import compose, relative
from scanguard.pairs.features import pair_metrics
from scanguard.pairs.labels import LabelConfig, assign_labels, non_finite_errors, pair_errors
from scanguard.pairs.odometry import OdometryNoise, odometry_sigmas
from scanguard.scan import ScanSequence

log = logging.getLogger(__name__)

#: Called after each pair with the number of pairs just done (for progress bars).
PairCallback = Callable[[int], None]


def name_seed(name: str, seed: int) -> int:
    """A seed from a name and a base seed (odometry noise per sequence, split shuffles)."""
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
    rng = np.random.default_rng(name_seed(name, noise.seed))
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
    matched = _match_pairs(seq, matcher, init, ref_rel, gmapping=gmapping, on_pair=on_pair)
    errs = matched.errors
    lab = assign_labels(errs[:, 0], errs[:, 1], errs[:, 2], labels)
    n_bad = _count_non_finite(seq, errs)
    full_meta: dict[str, Any] = {
        "labels": labels.model_dump(mode="json"),
        "matcher": matcher_name,
        "initial_guess": mode,
        "odometry_noise": noise.model_dump(mode="json") if mode == "simulated_odometry" else None,
        "source": jsonable(seq.metadata),
        "sensor": jsonable(seq.sensor.__dict__ if seq.sensor is not None else None),
    }
    if n_bad:
        full_meta["non_finite_pairs"] = n_bad
    full_meta.update(meta or {})
    pairs: dict[str, NDArray[Any]] = {
        "prev": np.arange(matched.n_pairs, dtype=np.int32),
        "curr": np.arange(1, matched.n_pairs + 1, dtype=np.int32),
        "estimate": matched.estimate,
        "initial": np.asarray(init, dtype=np.float64),
        "reference": ref_rel,
        "trans_error": errs[:, 0].copy(),
        "rot_error": errs[:, 1].copy(),
        "disp_error": errs[:, 2].copy(),
        "label": lab,
        "iterations": matched.iterations,
        "converged": matched.converged,
    }
    names = (environment, sequence, split)
    return _records(seq, names, pairs, matched.metrics, full_meta, (str(mode), matcher_name))


@dataclass
class _Matched:
    """The matches of a sequence's consecutive pairs and their errors (`_match_pairs`)."""

    estimate: NDArray[np.float64]
    errors: NDArray[np.float64]
    iterations: NDArray[np.int32]
    converged: NDArray[np.bool_]
    metrics: dict[str, NDArray[np.float64]]

    @property
    def n_pairs(self) -> int:
        """Number of pairs."""
        return int(self.estimate.shape[0])


def _match_pairs(
    seq: ScanSequence,
    matcher: Callable[..., Any],
    init: NDArray[np.float64],
    ref_rel: NDArray[np.float64],
    *,
    gmapping: bool,
    on_pair: PairCallback | None,
) -> _Matched:
    """Match pair ``k`` (scan ``k + 1`` onto scan ``k`` from ``init[k]``), measure its error."""
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
    return _Matched(est, errs, iters, conv, metrics)


def _count_non_finite(seq: ScanSequence, errs: NDArray[np.float64]) -> int:
    """Pairs whose errors are not finite (warned about; all of them: refused).

    Raises:
        InputError: No pair has a finite error.
    """
    n_pairs = errs.shape[0]
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
    return n_bad


def _records(
    seq: ScanSequence,
    names: tuple[str, str, str],
    pairs: dict[str, NDArray[Any]],
    metrics: dict[str, NDArray[np.float64]],
    meta: dict[str, Any],
    how: tuple[str, str],
) -> SequenceRecords:
    """The records of a labelled sequence.

    Args:
        seq: The sequence (with reference poses).
        names: Its environment, sequence and split names.
        pairs: The per-pair columns.
        metrics: The per-pair quality metrics.
        meta: Its provenance (``meta_json``).
        how: Initial-guess mode and matcher name (root attributes).
    """
    assert seq.reference is not None  # checked by label_sequence
    environment, sequence, split = names
    mode, matcher_name = how
    arrays = scans_to_arrays(seq.scans)
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
        pairs=pairs,
        metrics=metrics,
        attrs={
            "reference_kind": str(seq.reference_kind or "unknown"),
            "initial_guess": mode,
            "matcher": matcher_name,
            "name": seq.name,
        },
        meta=meta,
    )


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON types (what the file's ``meta_json`` will read back)."""
    return json.loads(json.dumps(obj, default=str, sort_keys=True))
