"""``scanguard run``: the guarded SLAM loop over a whole recording, next to the alternatives.

`run_recording` runs named phases, as kiss-icp's pipeline does:

1. **resolve** - the settings, the odometry (`resolve_odometry`), the relations, the gates and
   one back-end instance per gate (`scanguard.slam.registry`);
2. **loop** - one pass over the scans (`scanguard.slam.loop.RunLoop`): odometry only, the
   unguarded back end, and the back end guarded by the CNN, a classical baseline and the
   reference (oracle);
3. **score** - ATE/RPE, relations (Kümmerle et al.), the gates' agreement with the reference
   labels, the Fig. 19 centroid distance, latency;
4. **write** - trajectories, maps, figures, ``decisions.csv``, ``metrics.json``, ``summary.md``
   (`scanguard.apps.run_report`).

Odometry (`resolve_odometry`): ``auto`` uses the recorded odometry when it is usable (corrected
CARMEN logs have none), and otherwise none: odometry is never derived from the reference unless
asked for (``odometry="simulated"``, named ``simulated_from_reference`` in every output). A
recording without odometry runs with a motion prior that does not know the answer
(``RunConfig.prior``, see `scanguard.slam.loop`); outputs name the odometry
``none (zero-motion prior)`` or ``none (constant-velocity prior)``.

With Kümmerle et al.'s reference relations (``RunConfig.relations``, `find_relations`), every
trajectory is also scored on all relations and on those spanning at most
``relations_short_dt`` seconds, next to the published results.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.loop_setup import (
    adjust_without_odometry,
    build_instances,
    resolve_labels,
    scan_pairs,
)
from scanguard.apps.run_relations import check_relations, score_relations
from scanguard.apps.run_report import final_maps, write_run
from scanguard.apps.run_result import GateQuality, ResolvedRun, RunResult
from scanguard.apps.self_calibration import self_calibrate
from scanguard.detect.adaptive import AdaptiveThreshold
from scanguard.errors import ConfigError, InputError
from scanguard.fsutil import load_figure_writer
from scanguard.geometry import compose, relative, transform_points
from scanguard.pairs.labels import AMBIGUOUS, FAULT, NORMAL
from scanguard.pairs.odometry import OdometryNoise
from scanguard.scan import LaserScan, ScanSequence
from scanguard.slam.backend import Backend
from scanguard.slam.config import OdometryMode, Prior, RunConfig
from scanguard.slam.gate import Gate
from scanguard.slam.grid import chain, robot_to_sensor_increment
from scanguard.slam.guard import operating_point_detector
from scanguard.slam.judge import Detector, PairJudge, check_detector_matcher
from scanguard.slam.loop import (
    Instance,
    LoopObserver,
    LoopResult,
    LoopStep,
    RunLoop,
    instance_gates,
    trajectory_name,
)
from scanguard.slam.metrics import trajectory_errors

logger = logging.getLogger(__name__)

#: Odometry source names (`resolve_odometry`).
ODOMETRY_RECORDED = "recorded"
ODOMETRY_SIMULATED = "simulated_from_reference"
#: Odometry source of a recording without odometry, by prior.
ODOMETRY_NONE = {
    "zero_motion": "none (zero-motion prior)",
    "constant_velocity": "none (constant-velocity prior)",
}


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


def closure_counts(records: list[Any]) -> dict[str, int]:
    """Counts of a graph instance's loop-closure decisions (and their reference labels)."""
    return {
        "candidates": len(records),
        "accepted": sum(1 for r in records if r.added),
        "rejected": sum(1 for r in records if not r.verdict.accepted),
        "dropped_final": sum(1 for r in records if r.dropped_final),
        "withdrawn": sum(1 for r in records if r.withdrawn),
        "inconsistent": sum(1 for r in records if r.inconsistent),
        "agreed": sum(1 for r in records if r.agreed),
        "accepted_fault": sum(1 for r in records if r.added and r.label == FAULT),
        "rejected_normal": sum(1 for r in records if not r.added and r.label == NORMAL),
        "label_normal": sum(1 for r in records if r.label == NORMAL),
        "label_fault": sum(1 for r in records if r.label == FAULT),
    }


def _stats_ms(seconds: NDArray[np.float64]) -> tuple[float, float]:
    v = 1e3 * np.asarray(seconds, dtype=np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 95))


def _resolve(
    seq: ScanSequence,
    detector: Any,
    cfg: RunConfig,
    matcher: Callable[..., Any] | None,
    backend_factory: Callable[[], Backend] | None,
) -> ResolvedRun:
    """Phase 1: check the detector, cut the recording, choose odometry, read the relations."""
    from scanguard.matching import get_matcher

    # refuse a detector trained on another matcher's matches before any work
    check_detector_matcher(
        detector, cfg.matcher if matcher is None else matcher, allow_other=cfg.allow_other_matcher
    )
    # cut here, or by the reader (which stops reading there): relations may lie beyond
    cut = "max_scans" in seq.metadata
    if cfg.max_scans is not None and len(seq) > cfg.max_scans:
        seq, cut = seq.subsequence(slice(0, cfg.max_scans)), True
    if len(seq) < 2:
        raise InputError(None, f"sequence {seq.name!r} has {len(seq)} scan(s): need two or more")
    if cfg.rpe_delta >= len(seq):
        # evo would give NaN for every RPE figure, shown as if it were a number
        raise ConfigError(
            f"rpe_delta {cfg.rpe_delta} is not below the number of scans ({len(seq)}) of "
            f"{seq.name!r}: no relative pose error can be computed"
        )
    resolve_labels(cfg, detector)
    matcher_name = cfg.matcher if matcher is None else str(getattr(matcher, "name", "custom"))
    odom, source = resolve_odometry(seq, cfg.odometry_noise, cfg.odometry, prior=cfg.prior)
    if cfg.motion == "fused":
        source = (
            f"{source} wheels fused with judged {matcher_name} matches"
            if odom is not None
            else f"none: judged {matcher_name} matches fused with a constant-velocity prediction"
        )
    elif cfg.motion == "guarded_matches":
        source = f"guarded {matcher_name} matches, else {source}"
    if odom is None and cfg.motion != "guarded_matches":
        logger.warning(
            "%s: no usable odometry; running with odometry %s: each back end predicts its "
            "motion from its own estimate, nothing is taken from the reference",
            seq.name,
            source,
        )
        if backend_factory is None:
            adjust_without_odometry(seq.name, cfg)
    relations = published = note = None
    if cfg.relations is not None:
        from scanguard.io.relations import read_relations
        from scanguard.slam.relations import published_for

        relations = read_relations(cfg.relations)
        note = check_relations(relations, seq.stamps, cfg.relation_tolerance, cut=cut)
        if note is None:
            published = published_for(cfg.relations)
        else:  # a recording cut before the first relation: run, and say why no figure
            logger.warning("relations %s", note)
            relations = None
    ref = None if seq.reference is None else np.asarray(seq.reference, dtype=np.float64)
    start = ref[0] if ref is not None else (odom[0] if odom is not None else np.zeros(3))
    return ResolvedRun(
        seq=seq,
        cfg=cfg,
        odometry=odom,
        odometry_source=source,
        matcher=matcher if matcher is not None else get_matcher(cfg.matcher),
        matcher_name=matcher_name,
        start=np.asarray(start, dtype=np.float64),
        reference=ref,
        relations=relations,
        relations_note=note,
        published=published,
    )


def _instances(
    run: ResolvedRun,
    gates: dict[str, Gate],
    detector: Any,
    backend_factory: Callable[[], Backend] | None,
    observed: bool,
) -> dict[str, Instance]:
    """One back end per gate, from ``backend_factory`` or the registry.

    ``observed``: an observer reads every instance at every scan, so none runs in a worker.
    """
    seq = run.seq
    return build_instances(
        run.cfg,
        gates,
        detector,
        laser_offset=seq.laser_offset,
        start=run.start,
        range_max=None if seq.sensor is None else float(seq.sensor.range_max),
        reference=run.reference,
        backend_factory=backend_factory,
        n_scans=0 if observed else len(seq),
    )


def _asked(baseline: Any, run: ResolvedRun, instances: dict[str, Instance]) -> Any:
    """The classical detector where something reads its scores, else None (not computed).

    Its instance, the guard's policy, ``score_all`` and the gate-quality table of a run with a
    reference read them; with ``--no-compare`` and none of these, scoring every pair would
    cost ~0.4 ms a scan for a column no one asked for.
    """
    guard = run.cfg.guard
    wanted = (
        "baseline" in instances
        or guard.policy in ("baseline", "both")
        or guard.score_all
        or run.reference is not None
    )
    return baseline if wanted else None


def _loop(
    run: ResolvedRun,
    instances: dict[str, Instance],
    detector: Any,
    baseline: Any,
    on_step: Callable[[LoopStep, int, int], None] | None,
    observer: LoopObserver | None = None,
) -> LoopResult:
    """Phase 2: one pass over the scans, every instance fed the same verdicts."""
    seq, cfg = run.seq, run.cfg
    pairs = scan_pairs(
        cfg, run.matcher, detector, _asked(baseline, run, instances), seq.laser_offset
    )
    ref_sensor = None if run.reference is None else compose(run.reference, seq.laser_offset)
    loop = RunLoop(
        instances,
        pairs,
        cfg,
        odometry=run.odometry,
        start=run.start,
        reference_sensor=ref_sensor,
        on_step=on_step,
        observer=observer,
        on_wait=load_figure_writer,  # the figures written at the end, loaded while it waits
    )
    return loop.run(seq.scans)


def _trajectories(
    run: ResolvedRun, instances: dict[str, Instance], names: dict[str, str]
) -> dict[str, NDArray[np.float64]]:
    """The odometry trajectory and every instance's, checked to have one pose per scan."""
    n, odom = len(run.seq), run.odometry
    odo_inc = relative(odom[:-1], odom[1:]) if odom is not None else np.zeros((n - 1, 3))
    trajs: dict[str, NDArray[np.float64]] = {"odometry": chain(run.start, odo_inc)}
    for g, inst in instances.items():
        t = np.asarray(inst.backend.trajectory(), dtype=np.float64).reshape(-1, 3)
        if t.shape[0] != n:
            raise ConfigError(
                f"back end {inst.backend.name!r} returned {t.shape[0]} poses for {n} scans "
                f"({names[g]})"
            )
        trajs[names[g]] = t
    return trajs


def _result(
    run: ResolvedRun,
    loop: LoopResult,
    instances: dict[str, Instance],
    names: dict[str, str],
    trajs: dict[str, NDArray[np.float64]],
    baseline_info: str | None,
) -> RunResult:
    """The `RunResult` before scoring: setup, gate descriptions and counts."""
    judged = [s for s in loop.steps[1:] if s.judged]
    policy = instances["cnn"].gate
    gate_names = {
        names["cnn"]: f"guard policy {run.cfg.guard.policy}, CNN threshold "
        f"{policy.cnn_threshold:.3g} (the main result)",
    }
    if "none" in instances:
        gate_names[names["none"]] = "none (every scan usable)"
    baseline_name = str(run.baseline_name)
    if "baseline" in instances:
        gate_names[names["baseline"]] = (
            f"baseline {baseline_name}, threshold {policy.baseline_threshold:.3g}"
        )
    if "oracle" in instances:
        gate_names[names["oracle"]] = "oracle (reference labels)"
    c = loop.counts
    return RunResult(
        name=run.seq.name,
        n_scans=len(run.seq),
        odometry_source=run.odometry_source,
        reference_kind=run.seq.reference_kind if run.reference is not None else None,
        trajectories=trajs,
        backend=instances["cnn"].backend.name,
        matcher=run.matcher_name,
        gate_names=gate_names,
        baseline=None if "baseline" not in instances else (baseline_info or baseline_name),
        counts={
            "scans": len(run.seq),
            "judged": len(judged),
            "accepted": c.accepted,
            "rejected": c.rejected,
            "failed": c.failed,
            "skipped": c.skipped,
            **{f"wanted {names[g]}": int(loop.wanted[g].sum()) for g in instances},
            **{f"used {names[g]}": int(i.backend.used().sum()) for g, i in instances.items()},
            **{
                f"motion {k}": int(v)
                for k, v in loop.motion.get("cnn", {}).items()
                if not k.startswith("wheel_scale")
            },
        },
        rejected_mapped=run.cfg.maps_rejected_scans(),
        motion_scale={
            k: float(v)
            for k, v in loop.motion.get("cnn", {}).items()
            if k.startswith(("wheel_scale", "match_scale"))
        },
        relations_file=run.cfg.relations,
        relations_note=run.relations_note,
        published=run.published,
    )


def _score_gates(res: RunResult, loop: LoopResult, policy: Gate, baseline_name: str | None) -> None:
    """Agreement of the CNN, the baseline and accept-all with the reference labels."""
    judged = [s for s in loop.steps[1:] if s.judged]
    if not judged:
        return
    lab = np.array([loop.labels[s.index] for s in judged], dtype=np.int8)

    def faults(gate: Gate) -> NDArray[np.bool_]:
        return np.array([not gate.decide(s.verdict).accepted for s in judged])

    res.gates["cnn"] = _gate_quality("cnn", faults(policy.of_kind("cnn")), lab)
    if baseline_name is not None:
        res.gates["baseline"] = _gate_quality(
            f"baseline: {baseline_name}", faults(policy.of_kind("baseline")), lab
        )
    # accept-all only "flags" the pairs without a usable match
    res.gates["none"] = _gate_quality("none (accept all)", faults(policy.of_kind("none")), lab)
    res.counts["label_normal"] = int(np.sum(lab == NORMAL))
    res.counts["label_fault"] = int(np.sum(lab == FAULT))
    res.counts["label_ambiguous"] = int(np.sum(lab == AMBIGUOUS))


def _centroid(scan: LaserScan) -> NDArray[np.float64]:
    """Mean of a scan's points (NaN without any), its cached points released after."""
    p = scan.points(np.float64)
    mean = p.mean(axis=0) if len(p) else np.full(2, np.nan)
    scan.release()  # one scan's points at a time, not the whole recording's
    return mean


def _centroids(
    res: RunResult, seq: ScanSequence, trajs: dict[str, NDArray[np.float64]]
) -> dict[str, NDArray[np.float64]]:
    """Paper Fig. 19: centroid distance after the transform each method applied to the pair."""
    n = len(seq)
    means = np.array([_centroid(s) for s in seq])
    centroids: dict[str, NDArray[np.float64]] = {}
    for name, t in trajs.items():
        inc = robot_to_sensor_increment(relative(t[:-1], t[1:]), seq.laser_offset)
        moved = np.array([transform_points(inc[k], means[k + 1][None])[0] for k in range(n - 1)])
        centroids[name] = np.hypot(*(means[:-1] - moved).T)
        finite = centroids[name][np.isfinite(centroids[name])]
        # scans without a valid beam have no centroid: NaN (null in metrics.json), no warning
        res.centroid[name] = float(finite.mean()) if len(finite) else float("nan")
    return centroids


def _latency(
    res: RunResult, loop: LoopResult, policy: str, has_baseline: bool, guarded: str
) -> None:
    """The guard's stages over the pairs it judged; the guarded back end over every scan."""
    judged = [s for s in loop.steps[1:] if s.judged]
    if judged:
        for key, stage in (
            ("match", "match"),
            ("detect", "detect (render + CNN)"),
            ("baseline", "baseline"),
            ("total", "guard total"),
        ):
            if key == "baseline" and not has_baseline:
                continue
            res.latency_ms[stage] = _stats_ms(np.array([s.timings.get(key, 0.0) for s in judged]))
        # what a deployed guard with the configured policy costs: the run also scores the
        # detector it does not use (for the side-by-side instances), which `total` includes
        unused = {"cnn": "baseline", "baseline": "detect"}.get(policy)
        if unused is not None and has_baseline:
            res.latency_ms[f"guard ({policy} policy only)"] = _stats_ms(
                np.array([s.timings["total"] - s.timings.get(unused, 0.0) for s in judged])
            )
    t_cnn = loop.backend_seconds["cnn"]
    res.latency_ms[f"{guarded} update"] = _stats_ms(t_cnn)
    want = loop.wanted["cnn"][1:]
    if want.any() and not want.all():
        res.latency_ms[f"{guarded} update (scans it wanted)"] = _stats_ms(t_cnn[1:][want])


def _score(
    res: RunResult,
    run: ResolvedRun,
    loop: LoopResult,
    instances: dict[str, Instance],
    names: dict[str, str],
) -> dict[str, NDArray[np.float64]]:
    """Phase 3: errors, gate quality, relations, centroids, latency, closures; the centroids."""
    trajs = res.trajectories
    policy = instances["cnn"].gate
    if run.reference is not None:
        for name, t in trajs.items():
            res.errors[name] = trajectory_errors(
                run.seq.stamps, t, run.reference, delta=run.cfg.rpe_delta
            ).as_dict()
        _score_gates(res, loop, policy, run.baseline_name)
    if run.relations is not None:
        score_relations(res, run, trajs)
    centroids = _centroids(res, run.seq, trajs)
    _latency(res, loop, run.cfg.guard.policy, "baseline" in instances, names["cnn"])
    for g, inst in instances.items():
        if hasattr(inst.backend, "closures"):
            res.closures[names[g]] = closure_counts(list(inst.backend.closures))
    return centroids


def _gates(cfg: RunConfig, has_baseline: bool, has_reference: bool) -> list[str]:
    """The instances of a run: the guarded main one, and the comparisons unless not wanted."""
    if not cfg.compare:
        return ["cnn"]  # --no-compare: the main (guarded) instance alone
    return ["none", "cnn"] + ["baseline"] * has_baseline + ["oracle"] * has_reference


def _release_particle_maps(instances: dict[str, Instance]) -> None:
    """The result needs a map per instance, not per particle: give the particles' maps back."""
    for inst in instances.values():
        release = getattr(inst.backend, "release_particle_maps", None)
        if release is not None:
            release()


def _fit_odometry_noise(cfg: RunConfig, run: ResolvedRun, detector: Any) -> dict[str, float]:
    """``guard.fit_odometry_noise``: fit the robot's odometry noise, hand it to the detector."""
    if not cfg.guard.fit_odometry_noise:
        return {}
    learned = self_calibrate(
        run.seq, run.odometry, run.matcher, detector, min_points=cfg.guard.min_points
    )
    return learned or {}


def _operating_point(detector: Any) -> dict[str, Any]:
    """Where the adaptive operating point ended (empty with the fixed one)."""
    return dict(detector.summary()) if isinstance(detector, AdaptiveThreshold) else {}


def run_recording(
    seq: ScanSequence,
    detector: Detector,
    out_dir: str | Path,
    *,
    config: RunConfig | None = None,
    baseline: PairJudge | None = None,
    matcher: Callable[..., Any] | None = None,
    on_step: Callable[[LoopStep, int, int], None] | None = None,
    baseline_info: str | None = None,
    backend_factory: Callable[[], Backend] | None = None,
    observer: LoopObserver | None = None,
    self_calibration: dict[str, Any] | None = None,
) -> RunResult:
    """Run the guarded loop over ``seq`` with several back-end instances; write everything.

    See the module docstring for the phases, the odometry and the relations, and
    `scanguard.slam.loop` for the instances.

    Args:
        seq: The recording.
        detector: The CNN fault detector.
        out_dir: Output folder (created; files are written atomically).
        config: Settings (defaults if None). The resolved config is saved as ``config.yaml``.
        baseline: Classical detector of the ``+baseline`` instance, or None to skip it.
        matcher: Matcher override (default: ``config.matcher`` from the registry).
        on_step: Called after every scan with ``(step, n_accepted, n_rejected)``
            (progress display); skipped scans have reason ``"skipped"``.
        baseline_info: Where the baseline came from (see
            `scanguard.apps.run_baseline.resolve_baseline`), for the report.
        backend_factory: Builds one back-end instance per call (default: the registry's
            back end of ``config.backend``); every call must give an identical, independent
            instance.
        observer: Sees every scan and the final trajectories and maps (e.g. an MCAP sink).
        self_calibration: What ``run --self-calibrate`` changed in ``detector`` (reported).

    Returns:
        The `RunResult`.

    Raises:
        InputError: The sequence has fewer than two scans, the odometry asked for is not
            available, or the relations file does not match the recording.
        ConfigError: The back end is not available.
        ModelError: The detector was not trained on the matcher's matches and
            ``config.allow_other_matcher`` is off (raised before anything is written).
    """
    cfg = (config or RunConfig()).model_copy(deep=True)
    run = _resolve(seq, detector, cfg, matcher, backend_factory)
    learned = _fit_odometry_noise(cfg, run, detector)
    detector = operating_point_detector(cfg.guard, detector, cfg.backend)  # one per run
    if baseline is not None:
        run.baseline_name = str(getattr(baseline, "name", "baseline"))
    gates = _gates(cfg, baseline is not None, run.reference is not None)
    gate_of = instance_gates(cfg, gates, detector, baseline)
    instances = _instances(run, gate_of, detector, backend_factory, observer is not None)
    bname = instances["cnn"].backend.name
    names = {g: trajectory_name(bname, g) for g in gates}
    logger.info(
        "%s: %d scans, odometry %s, matcher %s, back end %s (%s)",
        run.seq.name,
        len(run.seq),
        run.odometry_source,
        run.matcher_name,
        bname,
        ", ".join(names.values()),
    )
    if observer is not None:
        observer.begin(run.seq, names)
    loop = _loop(run, instances, detector, baseline, on_step, observer)
    trajs = _trajectories(run, instances, names)
    _release_particle_maps(instances)
    if observer is not None:
        observer.end(*final_maps(run, instances, names, trajs))
    res = _result(run, loop, instances, names, trajs, baseline_info)
    res.learned, res.operating_point = learned, _operating_point(detector)
    res.self_calibration = dict(self_calibration or {})
    centroids = _score(res, run, loop, instances, names)
    res.files = write_run(Path(out_dir), run, res, loop, instances, names, centroids)
    return res
