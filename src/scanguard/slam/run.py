"""Run the guarded SLAM loop over a whole recording and compare it with the alternatives.

One pass over the scans feeds several instances of one SLAM back end (`scanguard.slam.backend`:
``gmapping``, the default, or ``frontend``, scan-to-scan chaining), all built with the same
settings and seed, and differing only in which scans they may use:

(a) ``odometry`` - odometry increments only (no back end);
(b) ``<backend>`` - unguarded: every scan is usable (for ``frontend``: plain ICP chaining);
(c) ``<backend>+cnn`` - guarded by the CNN (the guard's configured policy);
(d) ``<backend>+baseline`` - guarded by a classical detector (when one is given);
(e) ``<backend>+oracle`` - guarded by reference-based labels (`scanguard.pairs.labels`, the
    rule the training data was labelled with), computed on the fly for each judged pair: the upper
    bound of any gate (only with a reference).

The guard (`scanguard.slam.guard.ScanGuard`) judges a scan (match + CNN + baseline) only when
at least one instance ``wants_scan`` it, and only once; every instance then gets that verdict.
All instances see exactly the same matches.

Odometry (`resolve_odometry`): ``auto`` uses the recorded odometry when it is usable (corrected
CARMEN logs have none), and otherwise none: odometry is never derived from the reference unless
asked for (``odometry="simulated"``, named ``simulated_from_reference`` in every output). A
recording without odometry runs with a motion prior that does not know the answer
(``RunConfig.prior``): each back-end instance gets pseudo-odometry built from its *own*
estimate, either a constant pose (``zero_motion``) or its last pose increment repeated
(``constant_velocity``); outputs name the odometry ``none (zero-motion prior)`` or
``none (constant-velocity prior)``.

With Kümmerle et al.'s reference relations (``RunConfig.relations``, `find_relations`), every
trajectory is also scored on all relations and on those spanning at most
``relations_short_dt`` seconds, next to the published results.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from scanguard.config import YamlModel, save_config
from scanguard.errors import ConfigError, InputError, ModelError
from scanguard.fsutil import atomic_write_text
from scanguard.geometry import compose, relative, transform_points
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL, LabelConfig, assign_labels, pair_errors
from scanguard.pairs.odometry import OdometryNoise
from scanguard.scan import ScanSequence
from scanguard.slam.backend import Backend, FrontendBackend
from scanguard.slam.gmapping.config import GMappingConfig
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.grid import (
    build_map,
    chain,
    robot_to_sensor_increment,
    save_maps_figure,
)
from scanguard.slam.guard import (
    BaselineJudge,
    Decision,
    Detector,
    GuardConfig,
    PairJudge,
    ScanGuard,
    check_detector_matcher,
)
from scanguard.slam.metrics import (
    save_centroid_figure,
    save_trajectories_figure,
    trajectory_errors,
)

logger = logging.getLogger(__name__)

OdometryMode = Literal["auto", "recorded", "simulated"]
BackendName = Literal["gmapping", "frontend", "graph"]
Prior = Literal["zero_motion", "constant_velocity"]

#: Simulated scene of ``scanguard demo`` (a built-in `scanguard.sim` scenario name).
DEMO_SCENARIO = "lobby"
#: Simulated seconds of ``scanguard demo`` (``--fast`` / CI: `DEMO_FAST_DURATION`).
DEMO_DURATION = 30.0
#: Simulated seconds of ``scanguard demo --fast``.
DEMO_FAST_DURATION = 3.0
#: GMapping's ``lskip`` in the demo: its RPLidar has 1440 beams, and matching every 4th beam
#: (360, a SICK's density) is what a ROS user sets for such a scanner; maps use every beam.
DEMO_GMAPPING_LSKIP = 3

#: Gates of the back-end instances, in report order (``none`` = unguarded).
GATES = ("none", "cnn", "baseline", "oracle")
#: Odometry source names (`resolve_odometry`).
ODOMETRY_RECORDED = "recorded"
ODOMETRY_SIMULATED = "simulated_from_reference"
#: Odometry source of a recording without odometry, by prior.
ODOMETRY_NONE = {
    "zero_motion": "none (zero-motion prior)",
    "constant_velocity": "none (constant-velocity prior)",
}
_NAN3 = np.full(3, np.nan)


def trajectory_name(backend: str, gate: str) -> str:
    """Trajectory name of a back-end instance: ``gmapping`` (unguarded), ``gmapping+cnn``..."""
    return backend if gate == "none" else f"{backend}+{gate}"


def trajectory_names(backend: str) -> tuple[str, ...]:
    """All trajectory names of a run with ``backend``, in report order."""
    return ("odometry", *(trajectory_name(backend, g) for g in GATES))


class RunConfig(YamlModel):
    """Settings of `run_recording`.

    Attributes:
        backend: SLAM back end: ``gmapping`` (particle filter, `scanguard.slam.gmapping`),
            ``graph`` (pose graph with judged loop closures, `scanguard.slam.graph`) or
            ``frontend`` (scan-to-scan chaining of the guard's matches).
        gmapping: Settings of the ``gmapping`` back end (ROS names; ``seed`` seeds every
            instance identically).
        graph: Settings of the ``graph`` back end; each instance judges loop closures with its
            gate's judge (``none``: accept all, ``baseline``: the classical response test,
            ``cnn``: the detector, ``oracle``: the reference).
        matcher: Registered matcher name (the detector was trained on ``icp-paper`` matches).
        allow_other_matcher: Run with a matcher the CNN detector was not trained for
            (`scanguard.detect.detector.FaultDetector.check_matcher`; a warning, and its
            verdicts are then uncalibrated). Off: such a run is refused before it starts.
        guard: Loop settings; ``policy`` gates the ``+cnn`` instance; ``grid`` is the map of the
            ``frontend`` back end.
        odometry: Which odometry to use (see `resolve_odometry`).
        motion: What moves each back-end instance between scans: ``odometry`` (the odometry
            above, or the prior without one), or ``guarded_matches``: every scan is judged, and
            each instance moves by the guard's scan-to-scan match where its own gate accepts
            the match and by the odometry increment (or the prior) where it does not; the
            laser odometry a ROS user feeds GMapping when the wheels are bad, under the guard.
        odometry_noise: Noise of odometry simulated from the reference (``simulated`` only).
        prior: Motion prior of a recording without odometry (see the module docstring).
        labels: Labelling rule of the oracle (None = the detector's training rule, else the
            default `LabelConfig`).
        rpe_delta: RPE frame distance (1 = per scan pair).
        max_scans: Only use the first scans (None = all).
        relations: Kümmerle reference relations file (None = none; see `find_relations`).
        relations_short_dt: Relations spanning at most this many seconds are also scored
            separately.
    """

    backend: BackendName = "gmapping"
    gmapping: GMappingConfig = Field(default_factory=lambda: GMappingConfig())
    graph: GraphConfig = Field(default_factory=lambda: GraphConfig())
    matcher: str = "icp-paper"
    allow_other_matcher: bool = False
    guard: GuardConfig = Field(default_factory=lambda: GuardConfig())
    odometry: OdometryMode = "auto"
    odometry_noise: OdometryNoise = Field(default_factory=lambda: OdometryNoise())
    prior: Prior = "zero_motion"
    labels: LabelConfig | None = None
    rpe_delta: int = Field(default=1, ge=1)
    max_scans: int | None = Field(default=None, ge=2)
    relations: str | None = None
    relations_short_dt: float = Field(default=10.0, gt=0.0)
    motion: Literal["odometry", "guarded_matches"] = "odometry"


@dataclass
class GateQuality:
    """Agreement of a gate with the reference labels (ambiguous pairs excluded)."""

    name: str
    tp: int
    fp: int
    tn: int
    fn: int

    @property
    def n(self) -> int:
        """Labelled pairs compared."""
        return self.tp + self.fp + self.tn + self.fn

    @property
    def accuracy(self) -> float:
        """(TP + TN) / all."""
        return (self.tp + self.tn) / self.n if self.n else float("nan")

    @property
    def precision(self) -> float:
        """TP / (TP + FP) of the fault class."""
        d = self.tp + self.fp
        return self.tp / d if d else float("nan")

    @property
    def recall(self) -> float:
        """TP / (TP + FN) of the fault class."""
        d = self.tp + self.fn
        return self.tp / d if d else float("nan")

    def as_dict(self) -> dict[str, Any]:
        """Plain dict."""
        return {
            "name": self.name,
            "tp": self.tp,
            "fp": self.fp,
            "tn": self.tn,
            "fn": self.fn,
            "accuracy": self.accuracy,
            "precision": self.precision,
            "recall": self.recall,
        }


@dataclass
class RunResult:
    """Everything `run_recording` computed (also written to the output folder).

    Attributes:
        name: Sequence name.
        n_scans: Scans processed.
        odometry_source: ``recorded``, ``simulated_from_reference``,
            ``none (zero-motion prior)`` or ``none (constant-velocity prior)``.
        reference_kind: Reference kind of the sequence (None without a reference).
        trajectories: Name -> robot poses ``(N, 3)`` (see `trajectory_names`).
        backend: The SLAM back end (``gmapping`` or ``frontend``).
        matcher: The scan matcher of the guard.
        gate_names: Back-end trajectory name -> description of the gate that guarded it.
        errors: Name -> ATE/RPE dict (empty without a reference).
        gates: ``cnn``, ``baseline``, ``none`` (accept all) -> `GateQuality` over the judged
            pairs (empty without a reference).
        centroid: Name -> mean Fig. 19 centroid distance (m).
        counts: Guard counts (``judged``, ``accepted``, ``rejected``, ``failed``,
            ``skipped``), labels, and per instance ``used <name>`` (scans in its map).
        latency_ms: Stage -> (median, p95) per-scan latency (ms).
        baseline: What gated the ``+baseline`` instance (None without one).
        relations: Scope (``all``, ``dt <= 10 s``) -> trajectory -> `RelationErrors`
            (empty without relations).
        relations_file: The relations file used (None without).
        published: Published relation errors of that recording (method -> (mean, std) m).
        closures: ``graph`` only: instance name -> counts of its loop-closure decisions
            (`closure_counts`).
        files: Written files.
    """

    name: str
    n_scans: int
    odometry_source: str
    reference_kind: str | None
    trajectories: dict[str, NDArray[np.float64]]
    backend: str = "frontend"
    matcher: str = "icp-paper"
    gate_names: dict[str, str] = field(default_factory=dict)
    errors: dict[str, dict[str, Any]] = field(default_factory=dict)
    gates: dict[str, GateQuality] = field(default_factory=dict)
    centroid: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)
    baseline: str | None = None
    relations: dict[str, dict[str, Any]] = field(default_factory=dict)
    relations_file: str | None = None
    published: dict[str, tuple[float, float]] | None = None
    closures: dict[str, dict[str, int]] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)

    @property
    def unguarded(self) -> str:
        """Name of the unguarded back-end trajectory (the reference of `rpe_reduction`)."""
        return self.backend

    def setup(self, name: str) -> dict[str, str]:
        """What produced trajectory ``name``: odometry source, matcher, back end and gate.

        The gate is ``none`` (unguarded), ``cnn``, ``baseline`` or ``oracle`` (described in
        `gate_names`), ``-`` for the odometry trajectory.
        """
        if name == "odometry":
            return {"odometry": self.odometry_source, "matcher": "-", "back end": "-", "gate": "-"}
        gate = name.split("+", 1)[1] if "+" in name else "none"
        return {
            "odometry": self.odometry_source,
            "matcher": self.matcher,
            "back end": self.backend,
            "gate": gate,
        }

    def rpe_reduction(self, name: str) -> float:
        """Relative RPE (translation) reduction of ``name`` against the unguarded back end."""
        base_name = self.unguarded
        if base_name not in self.errors or name not in self.errors:
            return float("nan")
        base = self.errors[base_name]["rpe_trans_rmse"]
        return float(1.0 - self.errors[name]["rpe_trans_rmse"] / base) if base > 0 else 0.0


# --- the classical baseline of trajectory (d) -----------------------------------------------

#: GMapping's ``minimumScore`` convention (ROS wiki: "scores go up to 600+, try 50"), as a
#: fraction of the best possible score: the fallback threshold on ``gmapping_score_norm``.
GMAPPING_MIN_SCORE_FRACTION = 50.0 / 600.0
#: File name of a fitted baseline shipped next to the CNN weights (``scanguard/models/``).
SHIPPED_BASELINE_NAME = "baseline.json"


def shipped_baseline_path(matcher: str | None = None) -> Path:
    """Where a fitted baseline shipped with the package would be (per matcher, like the CNN).

    ``baseline.json`` goes with the default model (``icp-paper``); another matcher's, when one
    was fitted, is ``baseline-<matcher>.json``.
    """
    from importlib import resources

    folder = Path(str(resources.files("scanguard") / "models"))
    if matcher is not None and matcher != "icp-paper":
        own = folder / f"baseline-{matcher}.json"
        if own.is_file():
            return own
    return folder / SHIPPED_BASELINE_NAME


def default_dataset_dir() -> Path:
    """The paper dataset of a source checkout (``<repo>/data/paper``; may not exist)."""
    return Path(__file__).resolve().parents[2] / "data" / "paper"


def gmapping_fallback_baseline() -> Any:
    """GMapping's own rule: fault iff ``gmapping_score_norm < 50 / 600`` (no fitting)."""
    from scanguard.detect.baselines import ThresholdDetector

    return ThresholdDetector.from_dict(
        {
            "name": "gmapping (minimumScore 50/600)",
            "feature": "gmapping_score_norm",
            "direction": "low",
            "criterion": "balanced_accuracy",
            "threshold": GMAPPING_MIN_SCORE_FRACTION,
        }
    )


def fit_best_baseline(
    dataset: str | Path,
    names: list[str] | None = None,
    select_split: str = "val",
) -> tuple[Any, dict[str, float]]:
    """Fit classical baselines on a dataset's training split; keep the best on ``select_split``.

    The baselines are fitted by `scanguard.detect.evaluate.fit_baselines`, exactly as
    ``scanguard evaluate`` fits them: every baseline of `scanguard.detect.baselines.BASELINES`
    (or ``names``) on the ``train`` pairs, with its threshold chosen by the CNN's rule (maximum
    balanced accuracy) on the ``select_split`` pairs (the training pairs when that split has
    no labelled pairs of both classes). The best is the one with the highest balanced accuracy
    on the same selection pairs (ambiguous pairs excluded). Test pairs are never used.

    Args:
        dataset: A pair-store directory or file(s) accepted by `PairStore.open`.
        names: Baselines to try (default: all).
        select_split: Split the thresholds are chosen on and the best baseline is chosen by.

    Returns:
        ``(best fitted detector, {name: balanced accuracy on the selection split})``.

    Raises:
        ConfigError: The store has no labelled training pairs of both classes, or no baseline
            can be fitted on it.
    """
    from scanguard.dataset import PairStore
    from scanguard.detect.baselines import BASELINES
    from scanguard.detect.evaluate import fit_baselines

    store = PairStore.open(dataset)
    train = store.indices("train")
    y_train = np.asarray(store.records["label"])[train].astype(np.int64)
    if len(train) == 0 or not ((y_train == FAULT).any() and (y_train == NORMAL).any()):
        raise ConfigError(f"{dataset}: no labelled training pairs of both classes to fit baselines")
    wanted = names or list(BASELINES)
    fitted = fit_baselines(store, wanted, ("train",), (select_split,), skip_unfittable=True)
    if not fitted:
        raise ConfigError(f"{dataset}: none of the baselines {wanted} could be fitted")
    scores: dict[str, float] = {}
    best: Any = None
    for name, det in fitted.items():
        # balanced accuracy at the chosen threshold on the selection pairs (every baseline of
        # BASELINES uses that criterion)
        scores[name] = float("nan") if det.select_score is None else float(det.select_score)
        if best is None or scores[name] > scores[best.name]:
            best = det
    logger.info(
        "best baseline on %s: %s (balanced accuracy %.3f)",
        select_split,
        best.name,
        scores[best.name],
    )
    return best, scores


#: Version of the baseline fitting rule, part of the cache key of `cached_best_baseline`
#: (2: scale-free features, thresholds chosen on the validation split by the CNN's rule).
BASELINE_FIT_VERSION = 2


def baseline_cache_dir() -> Path:
    """Folder of cached fitted baselines (``$XDG_CACHE_HOME/scanguard`` or ``~/.cache/...``)."""
    import os

    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "scanguard"


def cached_best_baseline(dataset: str | Path) -> tuple[Any, dict[str, float]]:
    """`fit_best_baseline` on a dataset directory, cached by the content of its manifest.

    Fitting every baseline takes ~10-20 s on a loaded 2-core machine; the result only changes
    when the dataset does, so it is kept in `baseline_cache_dir` (a stale or unreadable cache
    file is simply refitted).
    """
    import hashlib

    from scanguard.detect.baselines import load_detector, save_detector

    data = Path(dataset)
    manifest = data / "manifest.json" if data.is_dir() else data
    try:
        digest = hashlib.sha1(manifest.read_bytes())
        digest.update(f"baseline-fit-v{BASELINE_FIT_VERSION}".encode())
        key = digest.hexdigest()[:16]
    except OSError:
        return fit_best_baseline(data)
    cache = baseline_cache_dir()
    det_path = cache / f"baseline-{key}.json"
    score_path = cache / f"baseline-{key}.scores.json"
    if det_path.is_file() and score_path.is_file():
        try:
            return load_detector(det_path), json.loads(score_path.read_text())
        except (ModelError, ValueError) as exc:
            logger.warning("ignoring unreadable cached baseline %s (%s)", det_path, exc)
    det, scores = fit_best_baseline(data)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        save_detector(det, det_path)
        atomic_write_text(score_path, json.dumps(scores))
    except OSError as exc:
        logger.warning("cannot cache the fitted baseline in %s (%s)", cache, exc)
    return det, scores


def resolve_baseline(
    spec: str | None = "auto", dataset: str | Path | None = None, matcher: str | None = None
) -> tuple[BaselineJudge | None, str]:
    """The classical detector gating trajectory (d), and a sentence saying where it came from.

    Args:
        spec: ``"none"``/None (no trajectory (d)); a path to a detector JSON
            (`scanguard.detect.baselines.save_detector`); a baseline name of
            `scanguard.detect.baselines.BASELINES` (fitted on ``dataset``); ``"gmapping-default"``
            (GMapping's ``minimumScore`` rule, `gmapping_fallback_baseline`); or ``"auto"``:
            the fitted baseline shipped in ``scanguard/models/baseline.json`` if present, else
            the best baseline fitted on the training split of ``dataset`` (default:
            `default_dataset_dir`) if it exists, else the GMapping rule.
        dataset: Pair store to fit on.
        matcher: The run's matcher: ``"auto"`` prefers the baseline shipped for it
            (`shipped_baseline_path`).

    Returns:
        ``(judge or None, description)``.

    Raises:
        ConfigError: A named baseline without a dataset to fit it on, or an unknown spec.
        ModelError: An unreadable detector file.
    """
    from scanguard.detect.baselines import BASELINES, load_detector

    if spec is None or spec == "none":
        return None, "none"
    data = Path(dataset) if dataset is not None else default_dataset_dir()
    if spec == "gmapping-default":
        det = gmapping_fallback_baseline()
        return BaselineJudge(det, "GMapping minimumScore rule"), (
            f"{det.name}: GMapping minimumScore convention, not fitted"
        )
    if spec in BASELINES:
        if not data.exists():
            raise ConfigError(
                f"baseline {spec!r} must be fitted, but dataset {data} does not exist"
            )
        det, scores = fit_best_baseline(data, [spec])
        return BaselineJudge(det, str(data)), (
            f"{det.name} fitted on the train split of {data} "
            f"(val balanced accuracy {scores[det.name]:.3f})"
        )
    if spec != "auto":
        p = Path(spec)
        if p.suffix == ".json" or p.exists():
            det = load_detector(p)
            return BaselineJudge(det, str(p)), f"{det.name} loaded from {p}"
        raise ConfigError(
            f"unknown baseline {spec!r}: use auto, none, gmapping-default, a detector JSON file "
            f"or one of {', '.join(BASELINES)}"
        )
    shipped = shipped_baseline_path(matcher)
    if shipped.is_file():
        det = load_detector(shipped)
        return BaselineJudge(
            det, str(shipped)
        ), f"{det.name} shipped with the model ({shipped.name})"
    if data.exists():
        try:
            det, scores = cached_best_baseline(data)
        except (ConfigError, InputError) as exc:
            logger.warning("cannot fit baselines on %s (%s): using the GMapping rule", data, exc)
        else:
            ranking = ", ".join(f"{k} {v:.3f}" for k, v in scores.items())
            return BaselineJudge(det, str(data)), (
                f"{det.name}, best of the baselines fitted on the train split of {data} "
                f"(val balanced accuracy: {ranking})"
            )
    det = gmapping_fallback_baseline()
    return BaselineJudge(det, "GMapping minimumScore rule"), (
        f"{det.name}: no shipped or fittable baseline, GMapping minimumScore convention"
    )


def resolve_odometry(
    seq: ScanSequence,
    noise: OdometryNoise,
    mode: OdometryMode = "auto",
    *,
    prior: Prior = "zero_motion",
) -> tuple[NDArray[np.float64] | None, str]:
    """Robot odometry poses ``(N, 3)`` to use for a sequence, and where they come from.

    Odometry is never derived from the reference unless ``mode="simulated"`` asks for it.

    Args:
        seq: The recording.
        noise: Noise of odometry simulated from the reference.
        mode: ``auto`` (recorded odometry when usable, else none), ``recorded`` (required) or
            ``simulated`` (from the reference with ``noise``, even when odometry was recorded:
            a controlled odometry quality for comparisons).
        prior: Motion prior used without odometry (only names the source).

    Returns:
        ``(poses or None, source)`` with source ``recorded``, ``simulated_from_reference``,
        ``none (zero-motion prior)`` or ``none (constant-velocity prior)``. Corrected CARMEN
        logs (``reference_kind == "corrected_log"``) have no usable recorded odometry.

    Raises:
        InputError: The requested odometry is not available.
    """
    from scanguard.dataset.labelling import simulated_odometry_steps

    usable = seq.odometry is not None and seq.reference_kind != "corrected_log"
    if mode == "recorded" and not usable:
        raise InputError(None, f"sequence {seq.name!r} has no usable recorded odometry")
    if mode == "simulated":
        if seq.reference is None:
            raise InputError(
                None, f"sequence {seq.name!r} has no reference to simulate odometry from"
            )
        ref = np.asarray(seq.reference, dtype=np.float64)
        steps = simulated_odometry_steps(relative(ref[:-1], ref[1:]), noise, seq.name)
        return chain(ref[0], steps), ODOMETRY_SIMULATED
    if usable:
        return np.asarray(seq.odometry, dtype=np.float64), ODOMETRY_RECORDED
    return None, ODOMETRY_NONE[prior]


#: Recording suffixes next to which `find_relations` looks for ``<stem>.relations``.
RELATION_RECORDING_SUFFIXES = (".clf.gz", ".clf", ".log.gz", ".log")


def find_relations(recording: str | Path) -> Path | None:
    """The ``<stem>.relations`` file next to a CARMEN recording, if there is one.

    ``intel.clf.gz``, ``intel.clf`` and ``intel.log`` all look for ``intel.relations`` in the
    same folder.

    Args:
        recording: Path of the recording.

    Returns:
        The relations file, or None (other formats, or no such file).
    """
    p = Path(recording)
    name = p.name
    for suffix in RELATION_RECORDING_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            candidate = p.with_name(name[: -len(suffix)] + ".relations")
            return candidate if candidate.is_file() else None
    return None


def reference_labels(
    seq: ScanSequence, estimates: NDArray[np.float64], labels: LabelConfig
) -> NDArray[np.int8]:
    """Labels of all consecutive pair matches against the reference (NaN estimates = faults)."""
    if seq.reference is None:
        raise InputError(None, f"sequence {seq.name!r} has no reference: cannot label")
    sensor = compose(np.asarray(seq.reference, dtype=np.float64), seq.laser_offset)
    ref_rel = relative(sensor[:-1], sensor[1:])
    errs = np.full((len(estimates), 3), np.nan)
    for k, est in enumerate(estimates):
        if np.all(np.isfinite(est)):
            errs[k] = pair_errors(est, ref_rel[k], seq.scans[k + 1].points(np.float64))
    diverged = ~np.all(np.isfinite(np.asarray(estimates, dtype=np.float64)), axis=1)
    return assign_labels(errs[:, 0], errs[:, 1], errs[:, 2], labels, diverged=diverged)


def _pair_label(
    estimate: NDArray[np.float64] | None,
    reference: NDArray[np.float64],
    points: NDArray[np.floating[Any]],
    labels: LabelConfig,
) -> int:
    """Reference label of one match (`reference_labels` for a single pair; None = fault)."""
    if estimate is None or not np.all(np.isfinite(estimate)):
        return FAULT
    t, r, d = pair_errors(estimate, reference, points)
    return int(assign_labels(np.array([t]), np.array([r]), np.array([d]), labels)[0])


def _gate_quality(name: str, fault: NDArray[np.bool_], labels: NDArray[np.int8]) -> GateQuality:
    known = labels != AMBIGUOUS
    f, y = fault[known], labels[known] == FAULT
    return GateQuality(
        name=name,
        tp=int(np.sum(f & y)),
        fp=int(np.sum(f & ~y)),
        tn=int(np.sum(~f & ~y)),
        fn=int(np.sum(~f & y)),
    )


def gmapping_backend_class() -> type | None:
    """`scanguard.slam.gmapping.GMappingBackend`, or None where this build lacks it."""
    try:
        import scanguard.slam.gmapping as gm
    except ImportError:
        return None
    cls = getattr(gm, "GMappingBackend", None)
    return cls if isinstance(cls, type) else None


def make_backend(
    config: RunConfig,
    *,
    laser_offset: Any = (0.0, 0.0, 0.0),
    initial_pose: Any = (0.0, 0.0, 0.0),
    range_max: float | None = None,
    closure_judge: Any = None,
    reference: Any = None,
) -> Backend:
    """A fresh back end of ``config.backend`` (every call gives an identical, independent one).

    Args:
        config: Run settings (``backend``, ``gmapping``, ``graph``, ``prior``, ``guard.grid``).
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose of the first scan.
        range_max: The sensor's maximum range (m), for GMapping's ``maxRange``.
        closure_judge: ``graph`` only: the loop-closure judge
            (`scanguard.slam.graph.closure.ClosureJudge`; None = accept all).
        reference: ``graph`` only: reference robot poses, to label closure candidates in the
            report (never used for estimation).

    Raises:
        ConfigError: The ``gmapping`` back end is not available in this build.
    """
    if config.backend == "graph":
        from scanguard.slam.graph import GraphBackend

        return GraphBackend(
            config.graph,
            laser_offset=laser_offset,
            initial_pose=initial_pose,
            range_max=range_max,
            closure_judge=closure_judge,
            reference=reference,
        )
    if config.backend == "frontend":
        return FrontendBackend(
            laser_offset=laser_offset,
            initial_pose=initial_pose,
            prior="constant_velocity"
            if config.prior == "constant_velocity"
            else "constant_position",
            grid=config.guard.grid,
        )
    cls = gmapping_backend_class()
    if cls is None:
        raise ConfigError(
            "the gmapping back end (scanguard.slam.gmapping.GMappingBackend) is not available "
            "in this build: use --backend frontend"
        )
    backend: Backend = cls(
        config.gmapping,
        laser_offset=tuple(float(v) for v in np.asarray(laser_offset).reshape(3)),
        initial_pose=tuple(float(v) for v in np.asarray(initial_pose).reshape(3)),
        range_max=range_max,
    )
    return backend


def _closure_judge(cfg: RunConfig, gate: str, detector: Any, laser_offset: Any, ref: Any) -> Any:
    """The loop-closure judge of a gate's ``graph`` instance (None for other back ends)."""
    if cfg.backend != "graph":
        return None
    from scanguard.slam.graph.closure import judge_for_gate

    ref_sensor = None if ref is None else compose(ref, laser_offset)
    return judge_for_gate(gate, cfg.graph.closures, detector=detector, reference_sensor=ref_sensor)


def closure_counts(records: list[Any]) -> dict[str, int]:
    """Counts of a graph instance's loop-closure decisions (and their reference labels)."""
    out = {
        "candidates": len(records),
        "accepted": sum(1 for r in records if r.added),
        "rejected": sum(1 for r in records if not r.verdict.accepted),
        "dropped_final": sum(1 for r in records if r.dropped_final),
        "accepted_fault": sum(1 for r in records if r.added and r.label == FAULT),
        "rejected_normal": sum(1 for r in records if not r.added and r.label == NORMAL),
        "label_normal": sum(1 for r in records if r.label == NORMAL),
        "label_fault": sum(1 for r in records if r.label == FAULT),
    }
    return out


def _graph_outputs(
    instances: dict[str, Any],
    names: dict[str, str],
    grids: dict[str, Any],
    out: Path,
    title: str,
) -> list[Path]:
    """closures_<instance>.csv for every graph instance, and graph.png over the maps."""
    from scanguard.slam.graph.plot import save_graph_figure

    files: list[Path] = []
    graph_panels: dict[str, Any] = {}
    for g, inst in instances.items():
        rows = [r.as_dict() for r in inst.closures]
        tag = names[g].replace("+", "_")
        buf = io.StringIO()
        fields = list(rows[0]) if rows else ["node", "target_node", "accepted"]
        w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        atomic_write_text(out / f"closures_{tag}.csv", buf.getvalue())
        files.append(out / f"closures_{tag}.csv")
        grid = grids.get(g)
        graph_panels[f"{names[g]} (closures: {inst.closure_judge.name})"] = (
            grid,
            inst.node_poses(),
            inst.edges,
            inst.closures,
        )
    files.append(save_graph_figure(graph_panels, out / "graph.png", title=f"{title}: pose graphs"))
    return files


def _decisions_csv(
    decisions: list[Decision],
    labels: dict[int, int],
    backend_ms: NDArray[np.float64],
) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "index",
            "stamp",
            "judged",
            "accepted",
            "reason",
            "fault_probability",
            "baseline_score",
            "label",
            "match_x",
            "match_y",
            "match_theta",
            "centroid_match",
            "t_match_ms",
            "t_detect_ms",
            "t_baseline_ms",
            "t_guard_ms",
            "t_backend_ms",
        ]
    )
    for d in decisions:
        lab = labels.get(d.index, "")
        w.writerow(
            [
                d.index,
                f"{d.stamp:.6f}",
                int(d.reason != "skipped"),
                int(d.accepted),
                d.reason,
                f"{d.fault_probability:.6g}",
                f"{d.baseline_score:.6g}",
                lab,
                *(f"{v:.6g}" for v in d.match_increment),
                f"{d.centroid_match:.6g}",
                *(
                    f"{1e3 * d.timings.get(k, 0.0):.3f}"
                    for k in ("match", "detect", "baseline", "total")
                ),
                f"{backend_ms[d.index]:.3f}",
            ]
        )
    return buf.getvalue()


def judged_text(counts: dict[str, int]) -> str:
    """One sentence on what the guard judged (from `RunResult.counts`)."""
    text = f"{counts.get('judged', 0)} pairs judged"
    if counts.get("skipped", 0):
        text += f" ({counts['skipped']} scans skipped: no back end wanted them)"
    return (
        f"{text}; {counts.get('accepted', 0)} accepted, {counts.get('rejected', 0)} rejected "
        f"({counts.get('failed', 0)} failed matches)"
    )


def _md_row(cells: list[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def summary_markdown(res: RunResult) -> str:
    """A markdown report of a run (what `scanguard run` prints, as text)."""
    lines = [
        f"# scanguard run: {res.name}",
        "",
        f"- scans: {res.n_scans}; odometry: {res.odometry_source}; matcher: {res.matcher}; "
        f"back end: {res.backend}; reference: {res.reference_kind or 'none'}",
        f"- guard: {judged_text(res.counts)}",
        f"- baseline gate ({trajectory_name(res.backend, 'baseline')}): {res.baseline or 'none'}",
        *(f"- gate of {k}: {v}" for k, v in res.gate_names.items()),
        "",
    ]
    setup_cols = ["odometry", "matcher", "back end", "gate"]
    if res.errors:
        lines += [
            _md_row(
                [
                    "trajectory",
                    *setup_cols,
                    "ATE RMSE (m)",
                    "RPE trans RMSE (m)",
                    "RPE rot RMSE (deg)",
                    f"RPE vs {res.unguarded}",
                    "centroid dist. (m)",
                ]
            ),
            "|" + "---|" * 10,
        ]
        for name, e in res.errors.items():
            red = res.rpe_reduction(name) if name != res.unguarded else 0.0
            s = res.setup(name)
            lines.append(
                _md_row(
                    [
                        name,
                        *(s[k] for k in setup_cols),
                        f"{e['ate_rmse']:.3f}",
                        f"{e['rpe_trans_rmse']:.4f}",
                        f"{e['rpe_rot_rmse_deg']:.3f}",
                        f"{-100 * red:+.1f} %",
                        f"{res.centroid.get(name, float('nan')):.4f}",
                    ]
                )
            )
        lines.append("")
    if res.relations:
        lines += [f"Relations: `{res.relations_file}` (Kümmerle et al. 2009); mean ± std.", ""]
        for scope, table in res.relations.items():
            lines += [
                f"Relations ({scope}):",
                "",
                _md_row(
                    [
                        "trajectory",
                        *setup_cols,
                        "relations used",
                        "trans. abs. (m)",
                        "trans. sq. (m²)",
                        "rot. abs. (deg)",
                        "rot. sq. (deg²)",
                    ]
                ),
                "|" + "---|" * 10,
            ]
            for name, r in table.items():
                s = res.setup(name)
                lines.append(
                    _md_row(
                        [
                            name,
                            *(s[k] for k in setup_cols),
                            f"{r.n_matched}/{r.n_selected} of {r.n_relations}",
                            f"{r.trans_mean:.3f} ± {r.trans_std:.3f}",
                            f"{r.trans_sq_mean:.3f} ± {r.trans_sq_std:.3f}",
                            f"{r.rot_mean_deg:.2f} ± {r.rot_std_deg:.2f}",
                            f"{r.rot_sq_mean:.2f} ± {r.rot_sq_std:.2f}",
                        ]
                    )
                )
            lines.append("")
        if res.published:
            lines += [
                "Published on this recording (Kümmerle et al. 2009, Table 1):",
                "",
                _md_row(["method", "trans. abs. (m)"]),
                "|---|---|",
                *(
                    _md_row([f"{k} (published)", f"{m:.3f} ± {sd:.3f}"])
                    for k, (m, sd) in res.published.items()
                ),
                "",
            ]
    if res.closures:
        lines += [
            "Loop closures (candidates the search proposed, and what each instance's judge did; "
            "labels from the reference when there is one):",
            "",
            _md_row(
                [
                    "instance",
                    "judge",
                    "candidates",
                    "accepted",
                    "rejected",
                    "dropped by final check",
                    "accepted but fault",
                    "rejected but normal",
                ]
            ),
            "|" + "---|" * 8,
        ]
        judges = {"": "none", "cnn": "cnn", "baseline": "classical", "oracle": "oracle"}
        for name, c in res.closures.items():
            gate = name.split("+", 1)[1] if "+" in name else ""
            lines.append(
                _md_row(
                    [
                        name,
                        judges.get(gate, gate),
                        str(c["candidates"]),
                        str(c["accepted"]),
                        str(c["rejected"]),
                        str(c["dropped_final"]),
                        str(c["accepted_fault"]),
                        str(c["rejected_normal"]),
                    ]
                )
            )
        lines.append("")
    if res.gates:
        lines += [
            _md_row(
                [
                    "gate",
                    "odometry",
                    "matcher",
                    "back end",
                    "judged pairs",
                    "accuracy",
                    "precision",
                    "recall",
                    "TP",
                    "FP",
                    "TN",
                    "FN",
                ]
            ),
            "|" + "---|" * 12,
        ]
        for g in res.gates.values():
            lines.append(
                _md_row(
                    [
                        g.name,
                        res.odometry_source,
                        res.matcher,
                        res.backend,
                        str(g.n),
                        f"{g.accuracy:.3f}",
                        f"{g.precision:.3f}",
                        f"{g.recall:.3f}",
                        *(str(v) for v in (g.tp, g.fp, g.tn, g.fn)),
                    ]
                )
            )
        lines.append("")
    if res.latency_ms:
        lines += [
            _md_row(["stage", "odometry", "matcher", "back end", "median (ms)", "p95 (ms)"]),
            "|" + "---|" * 6,
        ]
        for k, (m, p) in res.latency_ms.items():
            lines.append(
                _md_row([k, res.odometry_source, res.matcher, res.backend, f"{m:.2f}", f"{p:.2f}"])
            )
        lines.append("")
    return "\n".join(lines)


def _stats_ms(seconds: NDArray[np.float64]) -> tuple[float, float]:
    v = 1e3 * np.asarray(seconds, dtype=np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 95))


def _check_relations(relations: Any, stamps: NDArray[np.float64]) -> None:
    """Fail before the run (not after it) when no relation stamp matches a scan stamp."""
    from scanguard.slam.metrics import relation_errors

    relation_errors(stamps, np.zeros((len(stamps), 3)), relations)


def run_recording(
    seq: ScanSequence,
    detector: Detector,
    out_dir: str | Path,
    *,
    config: RunConfig | None = None,
    baseline: PairJudge | None = None,
    matcher: Callable[..., Any] | None = None,
    on_step: Callable[[Decision, int, int], None] | None = None,
    baseline_info: str | None = None,
    backend_factory: Callable[[], Backend] | None = None,
) -> RunResult:
    """Run the guarded loop over ``seq`` with several back-end instances; write everything.

    See the module docstring for the instances, the odometry and the relations.

    Args:
        seq: The recording.
        detector: The CNN fault detector.
        out_dir: Output folder (created; files are written atomically).
        config: Settings (defaults if None). The resolved config is saved as ``config.yaml``.
        baseline: Classical detector of the ``+baseline`` instance, or None to skip it.
        matcher: Matcher override (default: ``config.matcher`` from the registry).
        on_step: Called after every scan with ``(decision, n_accepted, n_rejected)``
            (progress display); skipped scans have reason ``"skipped"``.
        baseline_info: Where the baseline came from (see `resolve_baseline`), for the report.
        backend_factory: Builds one back-end instance per call (default: `make_backend` of
            ``config``); every call must give an identical, independent instance.

    Returns:
        The `RunResult`.

    Raises:
        InputError: The sequence has fewer than two scans, the odometry asked for is not
            available, or the relations file does not match the recording.
        ConfigError: The back end is not available.
        ModelError: The detector was not trained on the matcher's matches and
            ``config.allow_other_matcher`` is off (raised before anything is written).
    """
    from scanguard.io.tum import write_tum
    from scanguard.matching import get_matcher

    cfg = (config or RunConfig()).model_copy(deep=True)
    # refuse a detector trained on another matcher's matches before any work
    check_detector_matcher(
        detector, cfg.matcher if matcher is None else matcher, allow_other=cfg.allow_other_matcher
    )
    if cfg.max_scans is not None and len(seq) > cfg.max_scans:
        seq = seq.subsequence(slice(0, cfg.max_scans))
    if len(seq) < 2:
        raise InputError(None, f"sequence {seq.name!r} has {len(seq)} scan(s): need two or more")
    if cfg.labels is None:
        rule = getattr(detector, "label_thresholds", None)
        cfg.labels = LabelConfig.from_dict(dict(rule)) if rule else LabelConfig()
    label_rule = cfg.labels
    n = len(seq)
    stamps = seq.stamps

    odom, odom_source = resolve_odometry(seq, cfg.odometry_noise, cfg.odometry, prior=cfg.prior)
    if cfg.motion == "guarded_matches":
        used_matcher = cfg.matcher if matcher is None else str(getattr(matcher, "name", "custom"))
        odom_source = f"guarded {used_matcher} matches, else {odom_source}"
    elif odom is None:
        logger.warning(
            "%s: no usable odometry; running with odometry %s: each back end predicts its "
            "motion from its own estimate, nothing is taken from the reference",
            seq.name,
            odom_source,
        )
        if (
            backend_factory is None
            and cfg.backend == "gmapping"
            and cfg.gmapping.temporalUpdate < 0
        ):
            logger.warning(
                "%s: without odometry GMapping's linearUpdate/angularUpdate never trigger: "
                "setting temporalUpdate = 0 (process every scan)",
                seq.name,
            )
            cfg.gmapping = cfg.gmapping.model_copy(update={"temporalUpdate": 0.0})
        if (
            backend_factory is None
            and cfg.backend == "graph"
            and cfg.graph.minimum_time_interval < 0
        ):
            seq_m = cfg.graph.sequential
            wide = seq_m.model_copy(
                update={
                    "window_xy": max(seq_m.window_xy, 1.5),
                    "window_theta": max(seq_m.window_theta, 0.8),
                    "levels": max(seq_m.levels, 6),
                }
            )
            logger.warning(
                "%s: without odometry the graph's travel triggers never fire and its prior "
                "predicts badly: every scan is a node (minimum_time_interval = 0) and the "
                "sequential search window widens to +-%.1f m, +-%.1f rad",
                seq.name,
                wide.window_xy,
                wide.window_theta,
            )
            cfg.graph = cfg.graph.model_copy(
                update={"minimum_time_interval": 0.0, "sequential": wide, "odometry_is_prior": True}
            )
    relations = None
    published = None
    if cfg.relations is not None:
        from scanguard.io.relations import read_relations
        from scanguard.slam.metrics import published_for

        relations = read_relations(cfg.relations)
        _check_relations(relations, stamps)
        published = published_for(cfg.relations)

    out = Path(out_dir)

    match_fn = matcher if matcher is not None else get_matcher(cfg.matcher)
    ref = None if seq.reference is None else np.asarray(seq.reference, dtype=np.float64)
    start = ref[0] if ref is not None else (odom[0] if odom is not None else np.zeros(3))
    fallback = "constant_velocity" if cfg.prior == "constant_velocity" else "constant_position"
    gcfg = cfg.guard.model_copy(
        update={"score_all": True, "update_map": False, "fallback": fallback}
    )
    guard = ScanGuard(
        detector,
        match_fn,
        gcfg,
        baseline=baseline,
        laser_offset=seq.laser_offset,
        initial_pose=start,
        allow_other_matcher=True,  # checked (and warned about) above
    )
    range_max = None if seq.sensor is None else float(seq.sensor.range_max)
    gates = ["none", "cnn"]
    if baseline is not None:
        gates.append("baseline")
    if ref is not None:
        gates.append("oracle")
    if backend_factory is not None:
        instances = {g: backend_factory() for g in gates}
    else:
        instances = {
            g: make_backend(
                cfg,
                laser_offset=seq.laser_offset,
                initial_pose=start,
                range_max=range_max,
                closure_judge=_closure_judge(cfg, g, detector, seq.laser_offset, ref),
                reference=ref,
            )
            for g in gates
        }
    bname = instances["none"].name
    names = {g: trajectory_name(bname, g) for g in gates}
    logger.info(
        "%s: %d scans, odometry %s, matcher %s, back end %s (%s)",
        seq.name,
        n,
        odom_source,
        cfg.matcher if matcher is None else getattr(matcher, "name", "custom"),
        bname,
        ", ".join(names.values()),
    )

    ref_sensor = None if ref is None else compose(ref, seq.laser_offset)
    pseudo = {g: np.asarray(start, dtype=np.float64).copy() for g in gates}
    last_pose: dict[str, NDArray[np.float64] | None] = dict.fromkeys(gates)
    last_inc = {g: np.zeros(3) for g in gates}
    t_backend = {g: np.zeros(n) for g in gates}
    wanted = {g: np.zeros(n, dtype=bool) for g in gates}
    labels: dict[int, int] = {}
    decisions: list[Decision] = []
    motion_pose = {g: np.asarray(start, dtype=np.float64).copy() for g in gates}
    last_inc_zero = np.zeros(3)
    by_matches = cfg.motion == "guarded_matches"
    for k, scan in enumerate(seq.scans):
        if odom is None:
            if k > 0 and cfg.prior == "constant_velocity":
                for g in gates:
                    pseudo[g] = compose(pseudo[g], last_inc[g])
            odo_k = {g: pseudo[g].copy() for g in gates}
        else:
            odo_k = {g: odom[k] for g in gates}
        if by_matches:
            judge = True
        else:
            for g, inst in instances.items():
                wanted[g][k] = bool(inst.wants_scan(scan.stamp, odo_k[g]))
            judge = bool(any(wanted[g][k] for g in gates))
        d = guard.step(scan, None if odom is None else odom[k], judge=judge)
        decisions.append(d)
        match = None if d.match is None else np.asarray(d.match.pose, dtype=np.float64)
        if k == 0:
            verdict = dict.fromkeys(gates, True)
        elif d.reason == "skipped":
            verdict = {g: g == "none" for g in gates}
        else:
            ok = match is not None
            verdict = {"none": True, "cnn": bool(d.accepted)}
            if baseline is not None:
                s = d.baseline_score
                verdict["baseline"] = ok and bool(np.isfinite(s)) and s < guard.baseline_threshold
            if ref_sensor is not None:
                labels[k] = _pair_label(
                    match,
                    relative(ref_sensor[k - 1], ref_sensor[k]),
                    scan.points(np.float64),
                    label_rule,
                )
                verdict["oracle"] = ok and labels[k] != FAULT
        if by_matches:
            # each instance's own "odometry": its gate's accepted matches, else odometry/prior
            wheel = relative(odom[k - 1], odom[k]) if odom is not None and k > 0 else last_inc_zero
            for g, inst in instances.items():
                if k > 0:
                    use = verdict[g] and match is not None
                    step = np.asarray(d.match_increment) if use else wheel
                    if odom is None and not use and cfg.prior == "constant_velocity":
                        step = last_inc[g]
                    motion_pose[g] = compose(motion_pose[g], step)
                    if odom is None:
                        last_inc[g] = step
                odo_k[g] = motion_pose[g].copy()
                wanted[g][k] = bool(inst.wants_scan(scan.stamp, odo_k[g]))
        for g, inst in instances.items():
            t0 = time.perf_counter()
            inst.update(scan, odo_k[g], usable=verdict[g], match=match)
            t_backend[g][k] = time.perf_counter() - t0
            if odom is None and not by_matches:
                pose = np.asarray(inst.pose, dtype=np.float64).reshape(3)
                prev = last_pose[g]
                last_inc[g] = np.zeros(3) if prev is None else relative(prev, pose)
                last_pose[g] = pose.copy()
        if on_step is not None:
            on_step(d, guard.n_accepted, guard.n_rejected)
    guard.close()

    odo_inc = relative(odom[:-1], odom[1:]) if odom is not None else np.zeros((n - 1, 3))
    trajs: dict[str, NDArray[np.float64]] = {"odometry": chain(start, odo_inc)}
    for g, inst in instances.items():
        t = np.asarray(inst.trajectory(), dtype=np.float64).reshape(-1, 3)
        if t.shape[0] != n:
            raise ConfigError(
                f"back end {bname!r} returned {t.shape[0]} poses for {n} scans ({names[g]})"
            )
        trajs[names[g]] = t

    judged = [d for d in decisions[1:] if d.reason != "skipped"]
    gate_names = {
        names["none"]: "none (every scan usable)",
        names["cnn"]: f"guard policy {gcfg.policy}, CNN threshold {guard.cnn_threshold:.3g}",
    }
    if baseline is not None:
        gate_names[names["baseline"]] = (
            f"baseline {getattr(baseline, 'name', 'baseline')}, "
            f"threshold {guard.baseline_threshold:.3g}"
        )
    if ref is not None:
        gate_names[names["oracle"]] = "oracle (reference labels)"
    res = RunResult(
        name=seq.name,
        n_scans=n,
        odometry_source=odom_source,
        reference_kind=seq.reference_kind if ref is not None else None,
        trajectories=trajs,
        backend=bname,
        matcher=cfg.matcher if matcher is None else str(getattr(matcher, "name", "custom")),
        gate_names=gate_names,
        baseline=None
        if baseline is None
        else (baseline_info or str(getattr(baseline, "name", "baseline"))),
        counts={
            "scans": n,
            "judged": len(judged),
            "accepted": guard.n_accepted,
            "rejected": guard.n_rejected,
            "failed": guard.n_failed,
            "skipped": guard.n_skipped,
            **{f"wanted {names[g]}": int(wanted[g].sum()) for g in gates},
            **{f"used {names[g]}": int(instances[g].used().sum()) for g in gates},
        },
        relations_file=cfg.relations,
        published=published,
    )
    if ref is not None:
        for name, t in trajs.items():
            res.errors[name] = trajectory_errors(stamps, t, ref, delta=cfg.rpe_delta).as_dict()
        if judged:
            lab = np.array([labels[d.index] for d in judged], dtype=np.int8)
            ok_j = np.array([d.match is not None for d in judged])
            p_cnn = np.array([d.fault_probability for d in judged])
            cnn_fault = ~ok_j | (np.nan_to_num(p_cnn, nan=1.0) >= guard.cnn_threshold)
            res.gates["cnn"] = _gate_quality("cnn", cnn_fault, lab)
            if baseline is not None:
                s_base = np.array([d.baseline_score for d in judged])
                base_fault = ~ok_j | (np.nan_to_num(s_base, nan=np.inf) >= guard.baseline_threshold)
                res.gates["baseline"] = _gate_quality(
                    f"baseline: {getattr(baseline, 'name', 'baseline')}", base_fault, lab
                )
            res.gates["none"] = _gate_quality("none (accept all)", ~ok_j, lab)
            res.counts["label_normal"] = int(np.sum(lab == NORMAL))
            res.counts["label_fault"] = int(np.sum(lab == FAULT))
            res.counts["label_ambiguous"] = int(np.sum(lab == AMBIGUOUS))

    if relations is not None:
        from scanguard.slam.metrics import relation_errors

        short = cfg.relations_short_dt
        res.relations["all"] = {k: relation_errors(stamps, t, relations) for k, t in trajs.items()}
        try:
            res.relations[f"dt <= {short:g} s"] = {
                k: relation_errors(stamps, t, relations, max_dt=short) for k, t in trajs.items()
            }
        except InputError as exc:
            logger.warning("no relations spanning at most %g s: %s", short, exc)

    # paper Fig. 19: centroid distance after the transform each method applied to the pair
    means = np.array(
        [
            p.mean(axis=0) if len(p) else (np.nan, np.nan)
            for p in (s.points(np.float64) for s in seq)
        ]
    )
    centroids: dict[str, NDArray[np.float64]] = {}
    for name, t in trajs.items():
        inc = robot_to_sensor_increment(relative(t[:-1], t[1:]), seq.laser_offset)
        moved = np.array([transform_points(inc[k], means[k + 1][None])[0] for k in range(n - 1)])
        centroids[name] = np.hypot(*(means[:-1] - moved).T)
        finite = centroids[name][np.isfinite(centroids[name])]
        # scans without a valid beam have no centroid: NaN (null in metrics.json), no warning
        res.centroid[name] = float(finite.mean()) if len(finite) else float("nan")

    # latency: the guard's stages over the pairs it judged; the back end over every scan
    if judged:
        for key, stage in (
            ("match", "match"),
            ("detect", "detect (render + CNN)"),
            ("baseline", "baseline"),
            ("total", "guard total"),
        ):
            if key == "baseline" and baseline is None:
                continue
            res.latency_ms[stage] = _stats_ms(np.array([d.timings.get(key, 0.0) for d in judged]))
        # what a deployed guard with the configured policy costs: the run also scores the
        # detector it does not use (for the side-by-side instances), which `total` includes
        unused = {"cnn": "baseline", "baseline": "detect"}.get(cfg.guard.policy)
        if unused is not None and baseline is not None:
            res.latency_ms[f"guard ({cfg.guard.policy} policy only)"] = _stats_ms(
                np.array([d.timings["total"] - d.timings.get(unused, 0.0) for d in judged])
            )
    guarded_name = names["cnn"]
    res.latency_ms[f"{guarded_name} update"] = _stats_ms(t_backend["cnn"])
    want = wanted["cnn"][1:]
    if want.any() and not want.all():
        res.latency_ms[f"{guarded_name} update (scans it wanted)"] = _stats_ms(
            t_backend["cnn"][1:][want]
        )

    for g, inst in instances.items():
        if hasattr(inst, "closures"):
            res.closures[names[g]] = closure_counts(list(inst.closures))

    # outputs: only now, so that a failed run leaves no folder holding a config alone
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = [save_config(cfg, out)]
    atomic_write_text(
        out / "decisions.csv", _decisions_csv(decisions, labels, 1e3 * t_backend["cnn"])
    )
    files.append(out / "decisions.csv")
    for name, t in trajs.items():
        p = out / f"trajectory_{name.replace('+', '_')}.tum"
        write_tum(p, stamps, t)
        files.append(p)
    if ref is not None:
        write_tum(out / "trajectory_reference.tum", stamps, ref)
        files.append(out / "trajectory_reference.tum")
    grid_cfg = cfg.guard.grid
    if bname == "gmapping":
        grid_cfg = grid_cfg.model_copy(update={"resolution": cfg.gmapping.delta})
    panels: dict[str, Any] = {}
    panel_trajs: dict[str, NDArray[np.float64]] = {}
    gate_grids: dict[str, Any] = {}
    for g, title in (("none", f"{bname} (unguarded)"), ("cnn", f"{bname} + CNN gate")):
        grid = instances[g].grid()
        if grid is None:
            grid = build_map(
                seq.scans,
                trajs[names[g]],
                seq.laser_offset,
                include=instances[g].used(),
                config=grid_cfg,
            )
        tag = names[g].replace("+", "_")
        files.extend(grid.save_map_server(out / f"map_{tag}"))
        files.append(grid.save_png(out / f"map_{tag}.png"))
        panels[title] = grid
        gate_grids[g] = grid
        panel_trajs[title] = trajs[names[g]]
    if bname == "graph":
        files.extend(_graph_outputs(instances, names, gate_grids, out, seq.name))
    if ref is not None:
        panels["reference poses"] = build_map(seq.scans, ref, seq.laser_offset, config=grid_cfg)
        panel_trajs["reference poses"] = ref
    files.append(
        save_maps_figure(
            panels,
            out / "maps_side_by_side.png",
            trajectories=panel_trajs,
            title=f"{seq.name}: maps of {bname}, odometry {odom_source}",
        )
    )
    files.append(
        save_trajectories_figure(
            trajs,
            out / "trajectories.png",
            reference=ref,
            title=f"{seq.name} ({bname}, odometry {odom_source})",
        )
    )
    files.append(
        save_centroid_figure(
            {k: v for k, v in centroids.items() if k != "odometry"}, out / "centroid_distance.png"
        )
    )
    summary = {
        "name": res.name,
        "n_scans": n,
        "odometry_source": odom_source,
        "matcher": res.matcher,
        "backend": bname,
        "reference_kind": res.reference_kind,
        "trajectories": {k: res.setup(k) for k in trajs},
        "baseline": res.baseline,
        "baseline_threshold": guard.baseline_threshold if baseline is not None else None,
        "counts": res.counts,
        "errors": res.errors,
        "unguarded": res.unguarded,
        "rpe_reduction_vs_unguarded": {
            k: res.rpe_reduction(k) for k in res.errors if k != res.unguarded
        },
        "gates": {k: g.as_dict() for k, g in res.gates.items()},
        "centroid_distance_mean": res.centroid,
        "latency_ms": {k: {"median": m, "p95": p} for k, (m, p) in res.latency_ms.items()},
        "cnn_threshold": guard.cnn_threshold,
        "relations_file": res.relations_file,
        "relations": {
            scope: {k: r.as_dict() for k, r in table.items()}
            for scope, table in res.relations.items()
        },
        "relations_published": res.published,
        "backend_stats": {
            names[g]: dict(getattr(inst, "stats", {}) or {}) for g, inst in instances.items()
        },
        "closures": res.closures,
    }
    atomic_write_text(out / "metrics.json", strict_json(summary))
    atomic_write_text(out / "summary.md", summary_markdown(res))
    files += [out / "metrics.json", out / "summary.md"]
    res.files = files
    return res


def _json_safe(obj: Any) -> Any:
    """``obj`` with numpy values made plain and non-finite floats made None (JSON null)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def strict_json(obj: Any) -> str:
    """Standard JSON of ``obj`` (NaN and infinities become null: never bare ``NaN``)."""
    return json.dumps(_json_safe(obj), indent=2, allow_nan=False, default=str) + "\n"


def demo_sequence(*, fast: bool = False, seed: int = 7) -> ScanSequence:
    """The demo's simulated crowded scene (`DEMO_SCENARIO`).

    Args:
        fast: `DEMO_FAST_DURATION` instead of `DEMO_DURATION` simulated seconds (for CI).
        seed: Simulation seed.
    """
    from scanguard.sim import simulate

    return simulate(
        DEMO_SCENARIO, seed=seed, duration=DEMO_FAST_DURATION if fast else DEMO_DURATION
    )
