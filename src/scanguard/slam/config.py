"""Settings of a guarded SLAM run over a recording (`RunConfig`), read by the loop and the app."""

from __future__ import annotations

import multiprocessing
import os
from typing import Literal

from pydantic import Field

from scanguard.config import YamlModel
from scanguard.pairs.labels import LabelConfig
from scanguard.pairs.odometry import OdometryNoise
from scanguard.slam.gmapping.config import GMappingConfig
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.guard import GuardConfig
from scanguard.slam.motion import FusionConfig
from scanguard.slam.relations import RELATION_TOLERANCE

OdometryMode = Literal["auto", "recorded", "simulated"]
BackendName = Literal["gmapping", "frontend", "graph"]
Prior = Literal["zero_motion", "constant_velocity"]
#: ``instance_processes: auto`` puts the comparisons in worker processes from this many scans
#: (a worker takes ~1-2 s to start: the imports and the compiled kernels loaded from the cache;
#: `scanguard run` starts it while it reads the recording, `apps.loop_setup`).
PROCESS_MIN_SCANS = 1000


class RunConfig(YamlModel):
    """Settings of `scanguard.apps.run.run_recording`.

    Attributes:
        backend: SLAM back end: ``gmapping`` (particle filter, `scanguard.slam.gmapping`),
            ``graph`` (pose graph with judged loop closures, `scanguard.slam.graph`) or
            ``frontend`` (scan-to-scan chaining of the guard's matches). The default is
            ``graph``: chosen leave one log out on the three shared Freiburg logs (README,
            "The default back end"); GMapping, the paper's, stays one option away.
        gmapping: Settings of the ``gmapping`` back end (ROS names; ``seed`` seeds every
            instance identically).
        graph: Settings of the ``graph`` back end; each instance judges loop closures with its
            gate's judge (``none``: accept all, ``baseline``: the classical response test,
            ``cnn``: the detector, ``oracle``: the reference).
        matcher: Registered matcher name; the shipped detector of that matcher judges it.
            Default ``plicp`` (point-to-line ICP seeded by the wheels, `FusionConfig`): its
            Hessian is the fused motion's information of the match. The paper's ``icp-paper``
            stays in ``configs/run_paper.yaml``.
        allow_other_matcher: Run with a matcher the CNN detector was not trained for
            (`scanguard.detect.detector.FaultDetector.check_matcher`; a warning, and its
            verdicts are then uncalibrated). Off: such a run is refused before it starts.
        guard: Loop settings; ``policy`` gates the ``+cnn`` instance; ``grid`` is the map of the
            ``frontend`` back end.
        odometry: Which odometry to use (see `scanguard.apps.run.resolve_odometry`).
        motion: What moves each back-end instance between scans: ``odometry`` (the odometry
            above, or the prior without one), or ``guarded_matches``: every scan is judged, and
            each instance moves by the guard's scan-to-scan match where its own gate accepts
            the match and by the odometry increment (or the prior) where it does not; the
            laser odometry a ROS user feeds GMapping when the wheels are bad, under the guard;
            ``fused`` (default): every scan is judged, and each instance moves by the fused
            motion of the wheels, its accepted matches and a prediction
            (`scanguard.slam.motion`), weighted by their information.
        fusion: Settings of the fused motion model (``motion: fused``).
        rejected_scans: What a rejected match does to its scan in the back end (see
            `maps_rejected_scans`): ``dropped`` (the paper: odometry alone moves the robot and
            the scan is not mapped), ``mapped`` (the scan is still matched against the back
            end's map and mapped; only the motion loses the match), ``auto`` (``mapped`` with
            ``motion: fused``, else ``dropped``).
        odometry_noise: Noise of odometry simulated from the reference (``simulated`` only).
        prior: Motion prior of a recording without odometry (see the module docstring).
        labels: Labelling rule of the oracle (None = the detector's training rule, else the
            default `LabelConfig`).
        rpe_delta: RPE frame distance (1 = per scan pair).
        max_scans: Only use the first scans (None = all).
        relations: Kümmerle reference relations file (None = none; see `find_relations`).
        relations_short_dt: Relations spanning at most this many seconds are also scored
            separately.
        compare: Also run the comparisons next to the main (guarded) instance: the unguarded
            back end, the classical gate and, with a reference, the oracle gate (``False``:
            ``--no-compare``, the main instance alone).
        instance_threads: Threads that update the back-end instances of one scan side by side
            (they share nothing but the scan, so the results do not depend on it): 0 (default)
            one per instance up to the machine's cores for the ``graph`` back end, whose
            kernels release the GIL, and 1 for ``gmapping``, whose matching already runs its
            particles on every core; 1 one after the other.
        instance_processes: Run the comparison instances (unguarded, classical gate, oracle)
            in worker processes, fed the same values as in this one (``motion: fused`` only,
            where no instance's input depends on a back end; results identical,
            `scanguard.slam.detached`): ``on``, ``off``, or ``auto`` (default): on for the
            ``graph`` back end from `PROCESS_MIN_SCANS` scans, on a machine with two cores or
            more, in a process that is not itself a worker (``run-many``'s); one worker per
            core beyond the first. Threads gain little there: the Python between the kernels
            and gtsam's updates hold the GIL. GMapping's comparisons stay here: its matching
            already uses every core (a worker measured 0.93-1.08x, benchmarks/README.md).
            With no comparison (``compare: false``) the guarded instance itself goes to the
            worker, where its back end needs no CNN (the graph's learned closure judge reads
            a file): the guard and the back end then share no GIL (FR079 1.12x, trajectory
            byte-identical); with comparisons it stays here (all three in one worker measured
            0.77x).
        pipeline: The instances that stay in this process (the guarded one, and the
            comparisons where no worker takes them) update on a thread of their own, a few
            scans behind the guard, which meanwhile matches and judges the next scans on the
            other core (``motion: fused`` only, a whole recording without an observer; the
            same calls in the same order, so the results are identical,
            `scanguard.slam.detached`): ``on``, ``off``, or ``auto`` (default): on where
            the machine has two cores or more (FR079, graph: 1.2-1.35x faster alone,
            1.1-1.2x with the comparisons; GMapping and the front end 1.03-1.08x:
            benchmarks/README.md).
        relation_tolerance: A relation stamp takes the nearest scan stamp within this many
            seconds (`scanguard.slam.relations.relation_errors`); the run refuses a relations
            file of which fewer than 95 % of the relations inside the recording match.
    """

    backend: BackendName = "graph"
    gmapping: GMappingConfig = Field(default_factory=lambda: GMappingConfig())
    graph: GraphConfig = Field(default_factory=lambda: GraphConfig())
    matcher: str = "plicp"
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
    relation_tolerance: float = Field(default=RELATION_TOLERANCE, ge=0.0, le=10.0)
    compare: bool = True
    instance_threads: int = Field(default=0, ge=0, le=64)
    instance_processes: Literal["auto", "on", "off"] = "auto"
    pipeline: Literal["auto", "on", "off"] = "auto"
    motion: Literal["odometry", "guarded_matches", "fused"] = "fused"
    fusion: FusionConfig = Field(default_factory=lambda: FusionConfig())
    rejected_scans: Literal["auto", "dropped", "mapped"] = "auto"

    def instance_workers(self, n_instances: int) -> int:
        """Threads for ``n_instances`` back-end instances (`instance_threads` resolved)."""
        if self.instance_threads:
            return min(self.instance_threads, n_instances)
        if self.backend != "graph":
            return 1
        return max(1, min(n_instances, os.cpu_count() or 1))

    def worker_processes(self, n_scans: int, n_instances: int) -> int:
        """Worker processes for ``n_instances`` instances that may leave this one (0: none).

        Which instances may (the comparisons, or with no comparison the guarded one) is the
        caller's to say (`scanguard.apps.loop_setup.build_instances`); see
        ``instance_processes``.

        Args:
            n_scans: Scans of the recording.
            n_instances: Instances that could run in a worker.
        """
        if n_instances == 0 or self.motion != "fused" or self.instance_processes == "off":
            return 0
        cores = os.cpu_count() or 1
        if self.instance_processes == "auto" and (
            self.backend != "graph"
            or n_scans < PROCESS_MIN_SCANS
            or cores < 2
            or multiprocessing.parent_process() is not None
        ):
            return 0
        return max(1, min(n_instances, cores - 1))

    def pipelines(self) -> bool:
        """Whether the instances of this process update on a thread of their own (``pipeline``)."""
        if self.motion != "fused" or self.pipeline == "off":
            return False
        if self.pipeline == "on":
            return True
        return (os.cpu_count() or 1) >= 2

    def maps_rejected_scans(self) -> bool:
        """Whether a scan whose match the gate rejected still reaches the back end.

        ``auto``: yes with ``motion: fused``, where the verdict acts on the motion sources (a
        faulty match loses its term) and the back end's own scan-to-map matching weighs the
        scan; no otherwise (the paper: a rejected scan is discarded).
        """
        if self.rejected_scans != "auto":
            return self.rejected_scans == "mapped"
        return self.motion == "fused"

    def free_space_horizon(self) -> float:
        """Seconds of free-space views of the scan-to-scan matcher (``guard.free_space_horizon``).

        Unset, 3 s with the ``graph`` back end (the default, where leave one log out and the
        simulated crowds measured it) and 0 with the others (GMapping lost ACES with it: 0.046
        -> 0.064 m at filter seed 0).
        """
        if self.guard.free_space_horizon is not None:
            return float(self.guard.free_space_horizon)
        return 3.0 if self.backend == "graph" else 0.0

    def graph_settings(self, *, judged: bool = True) -> GraphConfig:
        """The graph back end's config as this run uses it (``graph``), for one instance.

        The far rule (``graph.closure_far_sigmas``) needs the fused motion's covariance,
        fitted on the recording; with ``motion: odometry`` (or ``laser``) the
        graph's sigmas come from a noise model, and ACES's right 7.9 m loop correction
        measured 3.4 of them on raw wheels (1.97 with the fused motion), so the rule would
        refuse it (relation error 0.043 -> 0.158 m): off there. Off too in an instance whose
        closures are not ``judged`` (the unguarded comparison, gate ``none``): the rule is a
        decision on closures, which that comparison leaves to the search; with it, the demo's
        unguarded run (slipping wheels never flagged) refused its right corrections and folded.
        """
        # decided here, not by whether a file named it: configs are merged through full
        # dumps (`scanguard.apps.config_merge`), where every field reads as named
        if self.motion == "fused" and judged:
            return self.graph
        return self.graph.model_copy(update={"closure_far_sigmas": None})

    def wheel_support(self) -> bool:
        """Whether the wheel-support test runs (``guard.wheel_support``).

        Unset, with the ``graph`` back end (the default since session 27: on 59 office
        stand-in seeds it mends the slides a person keeping pace causes; README "The
        wheel-support test, the default") and not with the others (GMapping on ACES: 0.0458 ->
        0.0486 m).
        """
        return self.guard.wheel_support_on(self.backend == "graph")

    def judge_reads_odometry(self) -> bool:
        """Whether the judge reads the odometry disagreement (``guard.judge_with_odometry``).

        Unset, it does not with ``motion: fused``: the fused motion model tests the wheels
        against each normal match itself (its wheel flag), and a judge that also read the
        wheels would reject a good match whenever the wheels lie.
        """
        if self.guard.judge_with_odometry is not None:
            return bool(self.guard.judge_with_odometry)
        return self.motion != "fused"
