"""Settings of the ``graph`` back end (pose graph with scan-to-map matching and loop closures).

Names follow slam_toolbox / Karto where a counterpart exists (``minimum_travel_distance``,
``loop_search_maximum_distance``, ``loop_match_minimum_chain_size``...), so a ROS user can
carry a tuned configuration over. Units: metres, radians, seconds.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from scanguard.config import YamlModel
from scanguard.matching.config import CorrelativeConfig
from scanguard.slam.graph.closure import ClosureJudgeConfig


def _sequential_matcher() -> CorrelativeConfig:
    # 5 cm cells: the correlative pass only has to land in the point-to-line refinement's
    # basin; a +-0.6 m window absorbs wheel odometry that is wrong by a node's travel (FR079).
    # Five levels (a top cell of 16 x 16): scoring the top level over ~160 angles was nearly
    # all of the search at four (16 top candidates per angle, median 2772 scored in all on
    # FR079); at five 4 per angle, 1112 in all, half the time, and the same poses (the
    # search is exact whatever the levels).
    return CorrelativeConfig(
        resolution=0.05, levels=5, window_xy=0.6, window_theta=0.4, sigma=0.05, min_score=0.1
    )


def _loop_matcher() -> CorrelativeConfig:
    # coarse and wide: a loop is closed after metres of drift; the fine pass then refines
    return CorrelativeConfig(
        resolution=0.05, levels=6, window_xy=3.0, window_theta=0.5, sigma=0.08, min_score=0.3
    )


def _loop_fine() -> CorrelativeConfig:
    return CorrelativeConfig(
        resolution=0.03, levels=3, window_xy=0.15, window_theta=0.1, sigma=0.05
    )


class GraphConfig(YamlModel):
    """Parameters of `scanguard.slam.graph.GraphBackend`.

    Attributes:
        minimum_travel_distance: Add a node (process a scan) after this much travel (m).
        minimum_travel_heading: ... or after this much rotation (rad).
        minimum_time_interval: ... or after this long (s); negative = never (needed without
            odometry, where the travel triggers cannot fire).
        local_map_nodes: Recent accepted nodes whose scans form the sequential matcher's map.
        local_map_max_distance: ... of those, only nodes within this of the predicted pose
            (m; Karto's ``scan_buffer_maximum_scan_distance``). With none left (after a long
            stretch of rejected scans, say), the node's scan seeds a new local map at its
            odometry pose.
        local_map_thin: The local map keeps the first point (newest node first) in each
            square of this lattice (m; 0: every point). Its scans, a node's travel apart,
            overlap a dozen times over, and the likelihood grid and the ICP refinement paid
            for every copy. 0.03 (session 20): the fastest lattice whose errors stayed within
            2 % of every point's on both training logs of each leave-one-log-out fold
            (README, "A thinned local map").
        carve_frames: Views that carve the local map before each sequential match: the scan
            being matched and the ``carve_frames - 1`` newest nodes remove older local-map
            points their beams passed beyond (people walking along with the robot; see
            `scanguard.slam.graph.local_map`). 0: no carving.
        carve_margin: A beam carves a point only when it reaches this far (m, plus 3 % of the
            range) beyond it, and so do both neighbouring beams.
        carve_lateral: ... and every beam within this many metres of it sideways.
        reseed_after_weak: After this many consecutive weak sequential matches, the next
            usable scan seeds a new local map at its odometry pose (a stale map cannot match).
        max_range: Beams at or beyond this are ignored by the matchers (m; None = sensor max).
        sequential: Correlative matcher of each node against the local map.
        refine: Refine matches with point-to-line ICP against the map points.
        min_response: A sequential match scoring below this is not added (odometry only).
        degenerate_probe: Probe the match's response this far (m) either way along its least
            certain direction...
        degenerate_tolerance: ... and when both probes score within this fraction of the best,
            the scan cannot tell where along that direction it is (a featureless corridor):
            the measurement slides back to the odometry prediction along it, and its variance
            there grows by ``degenerate_sigma`` squared, so odometry decides that direction.
        degenerate_sigma: See ``degenerate_tolerance`` (m).
        odom_sigma_xy: Odometry noise, metres per metre travelled (plus ``odom_floor_xy``).
            Loose on purpose: as in Karto, scan matches carry the graph and odometry mostly
            seeds them and bridges scans the guard rejected; wheel odometry that reports the
            wrong sign (FR079) must not pull a good match halfway.
        odom_sigma_theta: Odometry noise, radians per radian turned (plus ``odom_floor_theta``).
        odom_sigma_theta_per_m: Heading noise per metre travelled (rad/m).
        odom_floor_xy: Odometry noise floor per step (m).
        odom_floor_theta: Odometry noise floor per step (rad).
        match_covariance_scale: Multiplies the response-surface covariance of matches.
        loop_closure: Search for loop closures.
        loop_search_maximum_distance: Candidate nodes lie within this of the current estimate
            (the least reach when ``loop_search_sigmas`` is set).
        loop_search_sigmas: The reach follows the trajectory's uncertainty: this many
            standard deviations of the newest node's marginal position covariance (iSAM2's,
            against the first node; it grows with the travel since the last closure and
            shrinks when one is taken), at least ``loop_search_maximum_distance`` and at most
            ``loop_search_max_radius``; the coarse search window grows with it (position and
            heading), so a loop that drifted further than a fixed radius is still found
            (issue 30, building scale). Default 3 (session 19, chosen leave one log out on the
            shared logs, all three folds; on simulated buildings it cuts the ATE ~3x: README,
            "Loop search at building scale"). 0: the fixed reach above.
        loop_search_max_radius: The largest reach and coarse window (m) of that search.
        loop_window: The coarse window of a wide search. ``relative`` (default, session
            19): per candidate, ``loop_search_sigmas`` standard deviations of the two nodes'
            relative pose (iSAM2's joint marginal), at least the fixed window, so a place seen
            a few metres of path ago is searched narrowly even when the newest node is
            uncertain against the first one, and a loop that drifted far is searched as wide
            as its drift (simulated buildings: ATE 0.14 -> 0.09 m at half the loop-search
            time; README). ``marginal``: the newest node's reach for every candidate. The
            consistency gate bounds a claim by the same window.
        loop_wide_every: Only every n-th due search reaches that far (the others keep the
            fixed reach and window): a wide search costs up to ten times a fixed one, and a
            loop that drifted far is still there a few nodes later (Cartographer samples its
            global searches likewise).
        loop_match_minimum_chain_size: A candidate submap is a chain of at least this many
            consecutive nodes.
        loop_min_travel: Candidates lie at least this far back along the path (m), so the
            local map's own scans are never proposed as a loop.
        loop_search_every: Search once every this many nodes (cost bound).
        loop_fail_memory: A centre whose coarse loop search found nothing is not searched
            again for this many search rounds; its chain is searched at its nearest other
            node (`scanguard.slam.graph.loop_search.FailureMemory`). 0: off. The default, 5,
            was chosen by two leave-one-log-out folds of three over every search phase
            (README, "A building at hospital scale, and how fragile the graph's closures
            are"; the fold that held ACES out saw a tie and kept 0).
        closure_far_sigmas: A closure the judge accepted is refused when the correction it
            claims is beyond this many standard deviations of the graph's uncertainty and
            beyond ``closure_far_m`` metres (counted as ``closures_far``; None: off). In an
            office of alike rooms the search finds the room one along for a dozen nodes
            (2.8 m at 2.55 sigma, 3.2 m at 2.8), the learned judge accepts them, and two such
            candidates confirm each other; a right closure after a long drift the graph knows
            of is large in metres but not in sigmas (ACES: 7.4 m at 1.97). Precision first: a
            refused right closure leaves drift, an accepted wrong one folds the graph. The
            default since session 27 (README, "Closures that claim too much"), with the
            fused motion only: a run has it off with ``motion: odometry`` or ``laser`` and in
            its unguarded comparison (`scanguard.slam.config.RunConfig.graph_settings`).
        closure_far_m: See ``closure_far_sigmas`` (m).
        closure_far_agree: Candidates refused as too far wait for ``closure_agree_window``
            nodes; when this many from different nodes agree with each other
            (`scanguard.slam.graph.agreement.FarAgreement`), the graph is what is wrong (one
            wrong closure slipped in, or it drifted more than it knows): they enter together,
            and the closures the graph then contradicts by more than ``final_check_sigma``
            are withdrawn. The alike-room aliases of the office stand-in come in groups of at
            most 5; the right closures after a wrong one in groups of 58. 0: off.
        loop_search_phase: Nodes counted as already waiting when the run starts (``0 ..
            loop_search_every - 1``): which nodes are searched. Any phase is as good as
            another; `benchmarks/bench_fragility.py` runs each to see how much a result owes
            to the schedule.
        loop_submap_nodes: Nodes either side of a candidate's centre in its submap.
        loop_matcher: Correlative matcher of the coarse loop search (wide window; its
            ``min_score`` prunes the search, so a place that cannot match is rejected fast).
        loop_fine: Correlative matcher of the fine pass around the coarse result.
        loop_min_response: A coarse loop match scoring below this is not even a candidate.
        loop_alias_radius: Each candidate's coarse search is made again without the poses
            within this distance (m) of its result, to find its alias (a second peak one door
            along, an alike room; `scanguard.matching.correlative.second_peak`), written to
            ``closures_*.csv`` (``alias_ratio``, ``alias_m``, ``alias_sigmas``). 0 (the
            default): not searched. Measured with 1 m (README, "Aliased closures"): right
            and wrong closures alike have strong aliases, so no gate reads it yet, and it
            costs ~30 % more loop-search time.
        loop_alias_min_ratio: Only an alias scoring at least this fraction of the best
            response is looked for (branch-and-bound prunes the rest).
        loop_cooldown_nodes: After an accepted closure, skip this many nodes before searching
            again (a revisit yields one closure per pass, not one per node).
        robust_kernel: M-estimator on loop-closure factors: ``cauchy``, ``huber``,
            ``geman_mcclure`` (its pull fades to zero far out), ``dcs`` (dynamic covariance
            scaling, Agarwal et al. 2013; ``robust_scale`` is its Phi) or ``none``.
        robust_scale: Its scale, in standard deviations.
        batch_at_end: Run a batch Levenberg-Marquardt optimisation when the trajectory is read.
        final_check: After optimisation, drop accepted closures that the optimised graph
            contradicts by more than ``final_check_sigma`` standard deviations, and optimise
            again (the guard's third decision).
        final_check_sigma: Threshold of the final check (Mahalanobis distance).
        closure_agree_count: Candidates the judge refused (below ``closure_agree_max_p``)
            enter the graph together when this many agree pairwise on the correction they
            claim, within a normal closure's label thresholds (`scanguard.slam.graph.
            agreement`; session 20). 0 or 1: off (0, the default: leave one log out kept it off,
            and on Intel it admits consistent groups of wrong closures; docs/graph.md,
            "Doubted closures that agree").
        closure_agree_max_p: ... only candidates whose fault probability is below this wait
            for company (a probability judge's: the learned and the CNN closure judges).
        closure_agree_window: ... for at most this many nodes.
        closure_confirm_sigmas: A closure the judge accepted that claims a correction beyond
            this many standard deviations (`ClosureCandidate.disagreement_sigmas`) waits for
            a second candidate, from another node within ``closure_agree_window`` nodes, that
            claims the same correction; then both enter (`scanguard.slam.graph.agreement.
            ClosureConfirmation`). A wrong closure one door along is rarely confirmed, a
            right one after a drift is, by the next scans of the same revisit. None: off.
            The default, 1, was chosen leave one log out over every search phase, the
            hospital-scale stand-in deciding where the shared logs tie (README, "Every
            search phase").
        closure_gate_sigmas: A closure enters only when the correction it claims lies within
            this many standard deviations of the graph's own uncertainty about the two nodes
            (generously: iSAM2's marginals of both against the first node, plus the closure's
            covariance; translation and heading each) and within what a loop search could
            propose (its coarse window plus the fine one, per axis). Default 10 (session 18,
            chosen leave one log out on wrong closures injected into the shared logs; no
            searched closure of the default run was refused on any of them). 0: off.
        partial_relinearization: iSAM2 checks for relinearization only the cliques whose
            parents moved (gtsam's ``enablePartialRelinearizationCheck``), not every
            variable at every update: iSAM2 time 1.2-1.9x lower on Intel (3000-5000 scans),
            relation errors within 0.0015 m of before on the three Freiburg logs (session
            10, benchmarks/README.md). False: every variable (the results of before).
        odometry_noise: Noise of the odometry factor: ``model`` (the ``odom_*`` settings
            above) or ``fused`` (the fused motion model's per-scan covariances compounded
            between the nodes, `scanguard.slam.graph.odometry`, plus the floors; the model
            where a step's covariance is unknown). A node whose scan the guard dropped (no
            match factor holds it) always takes the fused covariance where there is one.
        fused_noise_scale: Scale of the fused covariance's sigmas (``odometry_noise: fused``).
        odometry_is_prior: The odometry given is a motion prior built from the graph's own
            estimate (the recording has none; `scanguard.apps.run` sets this): odometry
            factors become weak links (1 m, 1 rad) and matches never slide back to the
            prediction, which knows nothing.
        closures: Settings of the closure judges of a run's gates (classical thresholds,
            the detector's closure threshold, reference labelling).
        seed: Unused by the deterministic graph; kept for parity with the other back ends.
    """

    minimum_travel_distance: float = Field(default=0.1, ge=0.0)
    minimum_travel_heading: float = Field(default=0.2, ge=0.0)
    minimum_time_interval: float = -1.0
    local_map_nodes: int = Field(default=24, ge=1, le=1000)
    local_map_max_distance: float = Field(default=10.0, gt=0.0)
    local_map_thin: float = Field(default=0.03, ge=0.0, le=0.05)
    carve_frames: int = Field(default=0, ge=0, le=1000)
    carve_margin: float = Field(default=0.25, ge=0.0)
    carve_lateral: float = Field(default=0.0, ge=0.0)
    reseed_after_weak: int = Field(default=3, ge=1)
    max_range: float | None = Field(default=None, gt=0.0)
    sequential: CorrelativeConfig = Field(default_factory=_sequential_matcher)
    refine: bool = True
    min_response: float = Field(default=0.1, ge=0.0, le=1.0)
    degenerate_probe: float = Field(default=0.2, gt=0.0)
    degenerate_tolerance: float = Field(default=0.02, ge=0.0, lt=1.0)
    degenerate_sigma: float = Field(default=0.5, gt=0.0)
    odom_sigma_xy: float = Field(default=1.0, ge=0.0)
    odom_sigma_theta: float = Field(default=0.5, ge=0.0)
    odom_sigma_theta_per_m: float = Field(default=0.2, ge=0.0)
    odom_floor_xy: float = Field(default=0.01, gt=0.0)
    odom_floor_theta: float = Field(default=0.005, gt=0.0)
    match_covariance_scale: float = Field(default=1.0, gt=0.0)
    odometry_noise: Literal["model", "fused"] = "model"
    fused_noise_scale: float = Field(default=1.0, gt=0.0, le=100.0)
    loop_closure: bool = True
    loop_search_maximum_distance: float = Field(default=4.0, gt=0.0)
    loop_search_sigmas: float = Field(default=3.0, ge=0.0, le=100.0)
    loop_search_max_radius: float = Field(default=25.0, gt=0.0, le=1000.0)
    loop_window: Literal["marginal", "relative"] = "relative"
    loop_wide_every: int = Field(default=3, ge=1, le=1000)
    loop_match_minimum_chain_size: int = Field(default=5, ge=1)
    loop_min_travel: float = Field(default=8.0, ge=0.0)
    loop_search_every: int = Field(default=3, ge=1)
    loop_search_phase: int = Field(default=0, ge=0, le=1000)
    loop_fail_memory: int = Field(default=5, ge=0, le=1000)
    loop_submap_nodes: int = Field(default=6, ge=0)
    loop_matcher: CorrelativeConfig = Field(default_factory=_loop_matcher)
    loop_fine: CorrelativeConfig = Field(default_factory=_loop_fine)
    loop_min_response: float = Field(default=0.3, ge=0.0, le=1.0)
    loop_alias_radius: float = Field(default=0.0, ge=0.0, le=100.0)
    loop_alias_min_ratio: float = Field(default=0.7, gt=0.0, le=1.0)
    loop_cooldown_nodes: int = Field(default=10, ge=0)
    robust_kernel: Literal["cauchy", "huber", "geman_mcclure", "dcs", "none"] = "cauchy"
    robust_scale: float = Field(default=1.0, gt=0.0)
    batch_at_end: bool = True
    final_check: bool = False
    final_check_sigma: float = Field(default=5.0, gt=0.0)
    closure_gate_sigmas: float = Field(default=10.0, ge=0.0)
    closure_agree_count: int = Field(default=0, ge=0, le=100)
    closure_agree_max_p: float = Field(default=0.5, gt=0.0, le=1.0)
    closure_agree_window: int = Field(default=150, ge=1)
    closure_confirm_sigmas: float | None = Field(default=1.0, gt=0.0)
    closure_far_sigmas: float | None = Field(default=2.5, gt=0.0)
    closure_far_m: float = Field(default=1.5, gt=0.0)
    closure_far_agree: int = Field(default=10, ge=0, le=1000)
    partial_relinearization: bool = True
    odometry_is_prior: bool = False
    closures: ClosureJudgeConfig = Field(default_factory=ClosureJudgeConfig)
    seed: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> GraphConfig:
        if not math.isfinite(self.minimum_time_interval):
            raise ValueError("minimum_time_interval must be finite")
        return self
