"""Run the guarded SLAM front end over a whole recording and compare it with the alternatives.

One pass of `scanguard.slam.guard.ScanGuard` (CNN policy, every detector scored) produces the match
of every consecutive pair once; the trajectories of the other gates reuse those matches, so all
of them see exactly the same ICP results:

(a) ``odometry`` - odometry increments only;
(b) ``icp`` - plain ICP chaining (every usable match accepted);
(c) ``icp+cnn`` - ICP gated by the CNN (the streaming guard's own fused poses);
(d) ``icp+baseline`` - ICP gated by a classical detector (when one is given);
(e) ``icp+oracle`` - ICP gated by the reference-based labels (`scanguard.labels`, the same rule
    the training data was labelled with): the upper bound of any gate.

Odometry: recorded odometry is used when present (except corrected CARMEN logs, whose odometry
is not aligned with the scans). Otherwise, with a reference, odometry is simulated from the
reference with `scanguard.dataset.config.OdometryNoise` (per step
``sigma_xy = 1 cm + 5 % of the distance``, ``sigma_theta = 0.5 deg + 5 % of the turn + 1 deg/m``).
Without either, rejected steps keep the pose (``constant_position``). The output says which.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from scanguard.config import YamlModel, save_config
from scanguard.dataset.config import OdometryNoise
from scanguard.errors import ConfigError, InputError, ModelError
from scanguard.fsutil import atomic_write_text
from scanguard.geometry import compose, relative, transform_points
from scanguard.labels import AMBIGUOUS, FAULT, NORMAL, LabelConfig, assign_labels, pair_errors
from scanguard.scan import ScanSequence
from scanguard.slam.grid import (
    build_map,
    chain,
    fuse_increments,
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
)
from scanguard.slam.metrics import (
    save_centroid_figure,
    save_trajectories_figure,
    trajectory_errors,
)

logger = logging.getLogger(__name__)

OdometryMode = Literal["auto", "recorded", "simulated"]

#: Trajectory names, in report order.
TRAJECTORIES = ("odometry", "icp", "icp+cnn", "icp+baseline", "icp+oracle")
_NAN3 = np.full(3, np.nan)


class RunConfig(YamlModel):
    """Settings of `run_recording`.

    Attributes:
        matcher: Registered matcher name (the detector was trained on ``icp-paper`` matches).
        guard: Loop settings; ``policy`` decides trajectory (c) and the map.
        odometry: Which odometry to use (see `resolve_odometry`).
        odometry_noise: Noise of odometry simulated from the reference.
        labels: Labelling rule of the oracle (None = the detector's training rule, else the
            default `LabelConfig`).
        rpe_delta: RPE frame distance (1 = per scan pair).
        max_scans: Only use the first scans (None = all).
    """

    matcher: str = "icp-paper"
    guard: GuardConfig = Field(default_factory=lambda: GuardConfig())
    odometry: OdometryMode = "auto"
    odometry_noise: OdometryNoise = Field(default_factory=lambda: OdometryNoise())
    labels: LabelConfig | None = None
    rpe_delta: int = Field(default=1, ge=1)
    max_scans: int | None = Field(default=None, ge=2)


@dataclass
class GateQuality:
    """Agreement of a gate with the reference labels (ambiguous pairs excluded)."""

    name: str
    tp: int
    fp: int
    tn: int
    fn: int

    @property
    def accuracy(self) -> float:
        """(TP + TN) / all."""
        n = self.tp + self.fp + self.tn + self.fn
        return (self.tp + self.tn) / n if n else float("nan")

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
        odometry_source: ``recorded``, ``simulated_from_reference`` or ``none``.
        reference_kind: Reference kind of the sequence (None without a reference).
        trajectories: Name -> robot poses ``(N, 3)``.
        errors: Name -> ATE/RPE dict (empty without a reference).
        gates: Gate name -> `GateQuality` (empty without a reference).
        centroid: Name -> mean Fig. 19 centroid distance (m).
        counts: Accepted/rejected/failed counts of the streaming guard.
        latency_ms: Stage -> (median, p95) per-scan latency (ms).
        baseline: What gated trajectory (d) (None without one).
        files: Written files.
    """

    name: str
    n_scans: int
    odometry_source: str
    reference_kind: str | None
    trajectories: dict[str, NDArray[np.float64]]
    errors: dict[str, dict[str, Any]] = field(default_factory=dict)
    gates: dict[str, GateQuality] = field(default_factory=dict)
    centroid: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)
    baseline: str | None = None
    files: list[Path] = field(default_factory=list)

    def rpe_reduction(self, name: str = "icp+cnn") -> float:
        """Relative RPE (translation) reduction of ``name`` against plain ICP (0.75 = -75 %)."""
        if "icp" not in self.errors or name not in self.errors:
            return float("nan")
        base = self.errors["icp"]["rpe_trans_rmse"]
        return float(1.0 - self.errors[name]["rpe_trans_rmse"] / base) if base > 0 else 0.0


# --- the classical baseline of trajectory (d) -----------------------------------------------

#: GMapping's ``minimumScore`` convention (ROS wiki: "scores go up to 600+, try 50"), as a
#: fraction of the best possible score: the fallback threshold on ``gmapping_score_norm``.
GMAPPING_MIN_SCORE_FRACTION = 50.0 / 600.0
#: File name of a fitted baseline shipped next to the CNN weights (``scanguard/models/``).
SHIPPED_BASELINE_NAME = "baseline.json"


def shipped_baseline_path() -> Path:
    """Where a fitted baseline shipped with the package would be."""
    from importlib import resources

    return Path(str(resources.files("scanguard") / "models" / SHIPPED_BASELINE_NAME))


def default_dataset_dir() -> Path:
    """The paper dataset of a source checkout (``<repo>/data/paper``; may not exist)."""
    return Path(__file__).resolve().parents[2] / "data" / "paper"


def gmapping_fallback_baseline() -> Any:
    """GMapping's own rule: fault iff ``gmapping_score_norm < 50 / 600`` (no fitting)."""
    from scanguard.baselines import ThresholdDetector

    return ThresholdDetector.from_dict(
        {
            "name": "gmapping (minimumScore 50/600)",
            "feature": "gmapping_score_norm",
            "direction": "low",
            "criterion": "balanced_accuracy",
            "threshold": GMAPPING_MIN_SCORE_FRACTION,
        }
    )


def _balanced_accuracy(pred: NDArray[np.int64], y: NDArray[np.int64]) -> float:
    pos, neg = y == FAULT, y == NORMAL
    if not pos.any() or not neg.any():
        return float("nan")
    return 0.5 * (float(np.mean(pred[pos] == 1)) + float(np.mean(pred[neg] == 0)))


def fit_best_baseline(
    dataset: str | Path,
    names: list[str] | None = None,
    select_split: str = "val",
) -> tuple[Any, dict[str, float]]:
    """Fit classical baselines on a dataset's training split; keep the best on ``select_split``.

    Every baseline of `scanguard.baselines.BASELINES` (or ``names``) is fitted on the
    ``train`` pairs and scored by balanced accuracy on the ``select_split`` pairs (ambiguous
    pairs excluded; the training pairs when that split is empty). Test pairs are never used.

    Args:
        dataset: A pair-store directory or file(s) accepted by `PairStore.open`.
        names: Baselines to try (default: all).
        select_split: Split used to choose among them.

    Returns:
        ``(best fitted detector, {name: balanced accuracy on the selection split})``.

    Raises:
        ConfigError: The store has no labelled training pairs of both classes.
    """
    from scanguard.baselines import BASELINES, make_baseline
    from scanguard.dataset import PairStore

    store = PairStore.open(dataset)
    rec = store.records
    # only columns the store really holds (a metric that is also a pair column, such as
    # ``converged``, can be listed in ``metric_names`` without being in ``records``)
    cols = [k for k in dict.fromkeys([*store.metric_names, "iterations", "converged"]) if k in rec]

    def table(idx: NDArray[np.int64]) -> dict[str, NDArray[Any]]:
        return {k: np.asarray(rec[k])[idx] for k in cols}

    train = store.indices("train")
    pick = store.indices(select_split)
    if len(pick) == 0:
        logger.warning(
            "dataset %s has no %r pairs: choosing on the training pairs", dataset, select_split
        )
        pick = train
    y_train = np.asarray(rec["label"])[train].astype(np.int64)
    if len(train) == 0 or not ((y_train == FAULT).any() and (y_train == NORMAL).any()):
        raise ConfigError(f"{dataset}: no labelled training pairs of both classes to fit baselines")
    y_pick = np.asarray(rec["label"])[pick].astype(np.int64)
    scores: dict[str, float] = {}
    best: Any = None
    for name in names or list(BASELINES):
        try:
            det = make_baseline(name).fit(table(train), y_train)
        except (ModelError, ValueError) as exc:  # a feature this store lacks, too few pairs
            logger.warning("baseline %s cannot be fitted on %s: %s", name, dataset, exc)
            continue
        scores[name] = _balanced_accuracy(det.predict(table(pick)), y_pick)
        if best is None or scores[name] > scores[best.name]:
            best = det
    if best is None:
        raise ConfigError(
            f"{dataset}: none of the baselines {names or list(BASELINES)} could be fitted"
        )
    logger.info(
        "best baseline on %s: %s (balanced accuracy %.3f)",
        select_split,
        best.name,
        scores[best.name],
    )
    return best, scores


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

    from scanguard.baselines import load_detector, save_detector

    data = Path(dataset)
    manifest = data / "manifest.json" if data.is_dir() else data
    try:
        key = hashlib.sha1(manifest.read_bytes()).hexdigest()[:16]
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
    spec: str | None = "auto", dataset: str | Path | None = None
) -> tuple[BaselineJudge | None, str]:
    """The classical detector gating trajectory (d), and a sentence saying where it came from.

    Args:
        spec: ``"none"``/None (no trajectory (d)); a path to a detector JSON
            (`scanguard.baselines.save_detector`); a baseline name of
            `scanguard.baselines.BASELINES` (fitted on ``dataset``); ``"gmapping-default"``
            (GMapping's ``minimumScore`` rule, `gmapping_fallback_baseline`); or ``"auto"``:
            the fitted baseline shipped in ``scanguard/models/baseline.json`` if present, else
            the best baseline fitted on the training split of ``dataset`` (default:
            `default_dataset_dir`) if it exists, else the GMapping rule.
        dataset: Pair store to fit on.

    Returns:
        ``(judge or None, description)``.

    Raises:
        ConfigError: A named baseline without a dataset to fit it on, or an unknown spec.
        ModelError: An unreadable detector file.
    """
    from scanguard.baselines import BASELINES, load_detector

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
    shipped = shipped_baseline_path()
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
    seq: ScanSequence, noise: OdometryNoise, mode: OdometryMode = "auto"
) -> tuple[NDArray[np.float64] | None, str]:
    """Robot odometry poses ``(N, 3)`` to use for a sequence, and where they come from.

    Args:
        seq: The recording.
        noise: Noise of odometry simulated from the reference.
        mode: ``auto`` (recorded odometry when usable, else simulated from the reference, else
            none), ``recorded`` or ``simulated`` (from the reference, even when odometry was
            recorded: a controlled odometry quality for comparisons).

    Returns:
        ``(poses or None, source)`` with source ``recorded``, ``simulated_from_reference`` or
        ``none``.

    Raises:
        InputError: The requested odometry is not available.
    """
    from scanguard.dataset.build import simulated_odometry_steps

    usable = seq.odometry is not None and seq.reference_kind != "corrected_log"
    if mode == "recorded" and not usable:
        raise InputError(None, f"sequence {seq.name!r} has no usable recorded odometry")
    if mode == "simulated" and seq.reference is None:
        raise InputError(None, f"sequence {seq.name!r} has no reference to simulate odometry")
    if usable and mode != "simulated":
        return np.asarray(seq.odometry, dtype=np.float64), "recorded"
    if seq.reference is not None:
        ref = np.asarray(seq.reference, dtype=np.float64)
        steps = simulated_odometry_steps(relative(ref[:-1], ref[1:]), noise, seq.name)
        return chain(ref[0], steps), "simulated_from_reference"
    return None, "none"


def reference_labels(
    seq: ScanSequence, estimates: NDArray[np.float64], labels: LabelConfig
) -> NDArray[np.int8]:
    """Labels of the pair matches against the reference (NaN estimates = faults)."""
    if seq.reference is None:
        raise InputError(None, f"sequence {seq.name!r} has no reference: cannot label")
    sensor = compose(np.asarray(seq.reference, dtype=np.float64), seq.laser_offset)
    ref_rel = relative(sensor[:-1], sensor[1:])
    errs = np.full((len(estimates), 3), np.nan)
    for k, est in enumerate(estimates):
        if np.all(np.isfinite(est)):
            errs[k] = pair_errors(est, ref_rel[k], seq.scans[k + 1].points(np.float64))
    return assign_labels(errs[:, 0], errs[:, 1], errs[:, 2], labels)


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


def _decisions_csv(decisions: list[Decision], labels: NDArray[np.int8] | None) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "index",
            "stamp",
            "accepted",
            "reason",
            "fault_probability",
            "baseline_score",
            "label",
            "match_x",
            "match_y",
            "match_theta",
            "pose_x",
            "pose_y",
            "pose_theta",
            "centroid_match",
            "centroid_applied",
            "t_match_ms",
            "t_detect_ms",
            "t_map_ms",
            "t_total_ms",
        ]
    )
    for d in decisions:
        lab = "" if labels is None or d.index == 0 else int(labels[d.index - 1])
        w.writerow(
            [
                d.index,
                f"{d.stamp:.6f}",
                int(d.accepted),
                d.reason,
                f"{d.fault_probability:.6g}",
                f"{d.baseline_score:.6g}",
                lab,
                *(f"{v:.6g}" for v in d.match_increment),
                *(f"{v:.6f}" for v in d.pose),
                f"{d.centroid_match:.6g}",
                f"{d.centroid_applied:.6g}",
                *(f"{1e3 * d.timings[k]:.3f}" for k in ("match", "detect", "map", "total")),
            ]
        )
    return buf.getvalue()


def summary_markdown(res: RunResult) -> str:
    """A markdown report of a run (what `scanguard run` prints, as text)."""
    lines = [
        f"# scanguard run: {res.name}",
        "",
        f"- scans: {res.n_scans}; odometry: {res.odometry_source}; "
        f"reference: {res.reference_kind or 'none'}",
        f"- guard: {res.counts.get('accepted', 0)} accepted, "
        f"{res.counts.get('rejected', 0)} rejected ({res.counts.get('failed', 0)} failed matches)",
        f"- baseline gate (icp+baseline): {res.baseline or 'none'}",
        "",
    ]
    if res.errors:
        lines += [
            "| trajectory | ATE RMSE (m) | RPE trans RMSE (m) | RPE rot RMSE (deg) | "
            "RPE vs plain ICP | centroid dist. (m) |",
            "|---|---|---|---|---|---|",
        ]
        for name, e in res.errors.items():
            red = res.rpe_reduction(name) if name != "icp" else 0.0
            c = res.centroid.get(name, float("nan"))
            lines.append(
                f"| {name} | {e['ate_rmse']:.3f} | {e['rpe_trans_rmse']:.4f} | "
                f"{e['rpe_rot_rmse_deg']:.3f} | {-100 * red:+.1f} % | {c:.4f} |"
            )
        lines.append("")
    if res.gates:
        lines += [
            "| gate | accuracy | precision | recall | TP | FP | TN | FN |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for g in res.gates.values():
            lines.append(
                f"| {g.name} | {g.accuracy:.3f} | {g.precision:.3f} | {g.recall:.3f} | "
                f"{g.tp} | {g.fp} | {g.tn} | {g.fn} |"
            )
        lines.append("")
    if res.latency_ms:
        lines += ["| stage | median (ms) | p95 (ms) |", "|---|---|---|"]
        for k, (m, p) in res.latency_ms.items():
            lines.append(f"| {k} | {m:.2f} | {p:.2f} |")
        lines.append("")
    return "\n".join(lines)


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
) -> RunResult:
    """Run the guarded loop over ``seq`` and write decisions, trajectories, metrics and maps.

    Args:
        seq: The recording.
        detector: The CNN fault detector.
        out_dir: Output folder (created; files are written atomically).
        config: Settings (defaults if None). The resolved config is saved as ``config.yaml``.
        baseline: Classical detector for trajectory (d), or None to skip it.
        matcher: Matcher override (default: ``config.matcher`` from the registry).
        on_step: Called after every scan with ``(decision, n_accepted, n_rejected)``
            (progress display).
        baseline_info: Where the baseline came from (see `resolve_baseline`), for the report.

    Returns:
        The `RunResult`.

    Raises:
        InputError: The sequence has fewer than two scans.
    """
    from scanguard.io.tum import write_tum
    from scanguard.matching import get_matcher

    cfg = (config or RunConfig()).model_copy(deep=True)
    if cfg.max_scans is not None and len(seq) > cfg.max_scans:
        seq = seq.subsequence(slice(0, cfg.max_scans))
    if len(seq) < 2:
        raise InputError(None, f"sequence {seq.name!r} has {len(seq)} scan(s): need two or more")
    if cfg.labels is None:
        rule = getattr(detector, "label_thresholds", None)
        cfg.labels = LabelConfig.from_dict(dict(rule)) if rule else LabelConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out)

    match_fn = matcher if matcher is not None else get_matcher(cfg.matcher)
    odom, odom_source = resolve_odometry(seq, cfg.odometry_noise, cfg.odometry)
    ref = None if seq.reference is None else np.asarray(seq.reference, dtype=np.float64)
    start = ref[0] if ref is not None else (odom[0] if odom is not None else np.zeros(3))
    gcfg = cfg.guard.model_copy(update={"score_all": True})
    guard = ScanGuard(
        detector,
        match_fn,
        gcfg,
        baseline=baseline,
        laser_offset=seq.laser_offset,
        initial_pose=start,
    )
    decisions: list[Decision] = []
    for i, scan in enumerate(seq.scans):
        d = guard.step(scan, None if odom is None else odom[i])
        decisions.append(d)
        if on_step is not None:
            on_step(d, guard.n_accepted, guard.n_rejected)
    guard.close()

    n = len(seq)
    steps = decisions[1:]
    match_inc = np.array([d.match_increment for d in steps])
    ok = np.all(np.isfinite(match_inc), axis=1)
    fallback = relative(odom[:-1], odom[1:]) if odom is not None else np.zeros((n - 1, 3))
    p_cnn = np.array([d.fault_probability for d in steps])
    s_base = np.array([d.baseline_score for d in steps])
    cnn_fault = ~ok | (np.nan_to_num(p_cnn, nan=1.0) >= guard.cnn_threshold)
    stamps = seq.stamps
    trajs: dict[str, NDArray[np.float64]] = {
        "odometry": chain(start, fallback),
        "icp": fuse_increments(start, match_inc, fallback, ok),
        "icp+cnn": np.array([d.pose for d in decisions]),
    }
    base_fault = None
    if baseline is not None:
        base_fault = ~ok | (np.nan_to_num(s_base, nan=np.inf) >= guard.baseline_threshold)
        trajs["icp+baseline"] = fuse_increments(start, match_inc, fallback, ~base_fault)
    labels = None
    if ref is not None:
        est = np.array(
            [
                np.asarray(d.match.pose, dtype=np.float64) if d.match is not None else _NAN3
                for d in steps
            ]
        )
        labels = reference_labels(seq, est, cfg.labels)
        trajs["icp+oracle"] = fuse_increments(start, match_inc, fallback, labels != FAULT)

    res = RunResult(
        name=seq.name,
        n_scans=n,
        odometry_source=odom_source,
        reference_kind=seq.reference_kind if ref is not None else None,
        trajectories=trajs,
        baseline=None
        if baseline is None
        else (baseline_info or str(getattr(baseline, "name", "baseline"))),
        counts={
            "accepted": guard.n_accepted,
            "rejected": guard.n_rejected,
            "failed": guard.n_failed,
        },
    )
    if ref is not None and labels is not None:
        for name, t in trajs.items():
            res.errors[name] = trajectory_errors(stamps, t, ref, delta=cfg.rpe_delta).as_dict()
        res.gates["cnn"] = _gate_quality("cnn", cnn_fault, labels)
        if base_fault is not None:
            res.gates["baseline"] = _gate_quality("baseline", base_fault, labels)
        res.gates["plain icp (accept all)"] = _gate_quality("plain icp (accept all)", ~ok, labels)
        res.counts["label_normal"] = int(np.sum(labels == NORMAL))
        res.counts["label_fault"] = int(np.sum(labels == FAULT))
        res.counts["label_ambiguous"] = int(np.sum(labels == AMBIGUOUS))

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
        res.centroid[name] = float(np.nanmean(centroids[name]))
    for key in ("match", "detect", "baseline", "map", "total"):
        v = 1e3 * np.array([d.timings.get(key, 0.0) for d in steps])
        res.latency_ms[key] = (float(np.median(v)), float(np.percentile(v, 95)))
    # what a deployed guard with the configured policy costs: the run also scores the detector
    # it does not use (for the side-by-side trajectories), which `total` includes
    unused = (
        "baseline"
        if cfg.guard.policy == "cnn"
        else "detect"
        if cfg.guard.policy == "baseline"
        else None
    )
    if unused is not None:
        v = 1e3 * np.array([d.timings["total"] - d.timings.get(unused, 0.0) for d in steps])
        res.latency_ms[f"total ({cfg.guard.policy} policy only)"] = (
            float(np.median(v)),
            float(np.percentile(v, 95)),
        )

    # outputs
    files: list[Path] = [out / "config.yaml"]
    atomic_write_text(out / "decisions.csv", _decisions_csv(decisions, labels))
    files.append(out / "decisions.csv")
    for name, t in trajs.items():
        p = out / f"trajectory_{name.replace('+', '_')}.tum"
        write_tum(p, stamps, t)
        files.append(p)
    if ref is not None:
        write_tum(out / "trajectory_reference.tum", stamps, ref)
        files.append(out / "trajectory_reference.tum")
    plain_map = build_map(seq.scans, trajs["icp"], seq.laser_offset, config=cfg.guard.grid)
    gated_map = guard.grid
    if gated_map is None:
        gated_map = build_map(
            seq.scans,
            trajs["icp+cnn"],
            seq.laser_offset,
            include=np.array([d.accepted for d in decisions]),
            config=cfg.guard.grid,
        )
    for tag, grid in (("icp", plain_map), ("icp_cnn", gated_map)):
        files.extend(grid.save_map_server(out / f"map_{tag}"))
        files.append(grid.save_png(out / f"map_{tag}.png"))
    files.append(
        save_maps_figure(
            {"plain ICP": plain_map, "ICP gated by the CNN": gated_map},
            out / "maps_side_by_side.png",
            trajectories={"plain ICP": trajs["icp"], "ICP gated by the CNN": trajs["icp+cnn"]},
            title=f"{seq.name}: maps from accepted scans",
        )
    )
    files.append(
        save_trajectories_figure(
            trajs, out / "trajectories.png", reference=ref, title=f"{seq.name} ({odom_source})"
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
        "reference_kind": res.reference_kind,
        "baseline": res.baseline,
        "baseline_threshold": guard.baseline_threshold if baseline is not None else None,
        "counts": res.counts,
        "errors": res.errors,
        "rpe_reduction_vs_icp": {k: res.rpe_reduction(k) for k in res.errors if k != "icp"},
        "gates": {k: g.as_dict() for k, g in res.gates.items()},
        "centroid_distance_mean": res.centroid,
        "latency_ms": {k: {"median": m, "p95": p} for k, (m, p) in res.latency_ms.items()},
        "cnn_threshold": guard.cnn_threshold,
    }
    atomic_write_text(out / "metrics.json", json.dumps(summary, indent=2, default=float))
    atomic_write_text(out / "summary.md", summary_markdown(res))
    files += [out / "metrics.json", out / "summary.md"]
    res.files = files
    return res


def demo_sequence(*, fast: bool = False, seed: int = 7) -> ScanSequence:
    """The demo's simulated crowded lobby (paper Environment 1 analogue).

    Args:
        fast: A few dozen scans instead of a few hundred (for CI).
        seed: Simulation seed.
    """
    from scanguard.sim import simulate

    return simulate("lobby", seed=seed, duration=3.0 if fast else 30.0)
