"""Online loop: gating, pose fusion on rejects, map hygiene, policies, independence."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from scipy.spatial import cKDTree

from scanguard.errors import ConfigError, MatchingError
from scanguard.geometry import compose, relative, transform_points
from scanguard.scan import LaserScan
from scanguard.slam.grid import build_map, chain
from scanguard.slam.guard import GuardConfig
from scanguard.slam.stream import ScanGuard
from tests.helpers import make_sequence, room_segments

BAD = np.array([0.45, -0.3, 0.15])


@dataclass
class Match:
    pose: np.ndarray
    ok: bool = True


class ScriptedMatcher:
    """Returns the true relative pose, except at ``bad`` steps (wrong by ``BAD``)."""

    def __init__(self, reference: np.ndarray, bad: set[int], offset=(0.0, 0.0, 0.0)) -> None:
        laser = compose(reference, np.asarray(offset, dtype=float))
        self.truth = relative(laser[:-1], laser[1:])
        self.bad = bad
        self.calls = 0
        self.initials: list[Any] = []

    def __call__(self, source, target, initial=None):
        i = self.calls
        self.calls += 1
        self.initials.append(initial)
        pose = self.truth[i].copy()
        if i + 1 in self.bad:
            pose = compose(pose, BAD)
        return Match(pose)


class AlignmentDetector:
    """Geometric test double for the CNN: fault when the median NN distance exceeds 5 cm."""

    threshold = 0.5

    def __init__(self) -> None:
        self.calls = 0

    def fault_probability(self, previous: LaserScan, current: LaserScan, pose) -> float:
        self.calls += 1
        moved = transform_points(np.asarray(pose), current.points(np.float64))
        d, _ = cKDTree(previous.points(np.float64)).query(moved)
        return float(np.median(d) > 0.05)


class ConstantJudge:
    name = "const"

    def __init__(self, value: float, threshold: float = 0.5) -> None:
        self.value = value
        self.threshold = threshold

    def score(self, previous, current, match) -> float:
        return self.value


@pytest.fixture(scope="module")
def seq():
    rng = np.random.default_rng(3)
    steps = np.column_stack(
        [rng.uniform(0.05, 0.12, 24), rng.uniform(-0.03, 0.03, 24), rng.uniform(-0.04, 0.04, 24)]
    )
    s = make_sequence(room_segments(), steps, start=(-2.0, -0.5, 0.1), noise=0.0)
    # drifting odometry: the true increments with a small bias, so it differs from the truth
    inc = relative(s.reference[:-1], s.reference[1:]) + np.array([0.01, 0.004, 0.003])
    s.odometry = chain((5.0, 1.0, -0.3), inc)
    return s


def run(guard: ScanGuard, seq, odometry: bool = True):
    return [
        guard.step(scan, None if not odometry else seq.odometry[i])
        for i, scan in enumerate(seq.scans)
    ]


def test_injected_faults_are_rejected_and_pose_follows_odometry(seq):
    bad = {4, 11, 17}
    guard = ScanGuard(
        AlignmentDetector(), ScriptedMatcher(seq.reference, bad), initial_pose=seq.reference[0]
    )
    decisions = run(guard, seq)
    rejected = {d.index for d in decisions if not d.accepted}
    assert rejected == bad
    assert [d.reason for d in decisions][:2] == ["first", "accepted"]
    assert all(decisions[i].reason == "rejected_cnn" for i in bad)
    odo_inc = relative(seq.odometry[:-1], seq.odometry[1:])
    true_inc = relative(seq.reference[:-1], seq.reference[1:])
    for d in decisions[1:]:
        expected = odo_inc[d.index - 1] if d.index in bad else true_inc[d.index - 1]
        np.testing.assert_allclose(d.applied_increment, expected, atol=1e-12)
        np.testing.assert_allclose(
            d.pose, compose(decisions[d.index - 1].pose, expected), atol=1e-9
        )
    # fused pose = truth except for the three odometry steps (bias 1 cm / 4 mm / 3 mrad each)
    err = relative(seq.reference[-1], decisions[-1].pose)
    assert 0.01 < np.hypot(err[0], err[1]) < 0.15
    assert guard.n_accepted == len(seq) - 3 and guard.n_rejected == 3
    # the Fig. 19 metric of the raw match is large on injected faults, small elsewhere
    c = np.array([d.centroid_match for d in decisions[1:]])
    is_bad = np.array([i in bad for i in range(1, len(seq))])
    assert c[is_bad].min() > 0.2 > c[~is_bad].max()


def test_plain_icp_policy_accepts_everything_and_drifts(seq):
    bad = {4, 11, 17}
    guard = ScanGuard(
        None,
        ScriptedMatcher(seq.reference, bad),
        GuardConfig(policy="none"),
        initial_pose=seq.reference[0],
    )
    decisions = run(guard, seq)
    assert all(d.accepted for d in decisions)
    err = relative(seq.reference[-1], decisions[-1].pose)
    assert np.hypot(err[0], err[1]) > 0.5


@pytest.mark.parametrize("background", [False, True])
def test_rejected_scan_never_touches_map(seq, background):
    bad = {6, 7, 15}
    guard = ScanGuard(
        AlignmentDetector(),
        ScriptedMatcher(seq.reference, bad),
        GuardConfig(map_in_background=background),
        initial_pose=seq.reference[0],
    )
    with guard:
        decisions = run(guard, seq)
    # background inserts: one timed job per accepted scan, finished once the grid is read
    assert len(guard.background_map_seconds) == (len(seq) - len(bad) if background else 0)
    accepted = np.array([d.accepted for d in decisions])
    assert set(np.flatnonzero(~accepted)) == bad
    poses = np.array([d.pose for d in decisions])
    ref_map = build_map(seq.scans, poses, include=accepted)
    assert guard.grid is not None
    assert guard.grid.shape == ref_map.shape
    np.testing.assert_allclose(guard.grid.origin, ref_map.origin)
    np.testing.assert_array_equal(guard.grid.logodds, ref_map.logodds)
    # inserting a rejected scan would change the map: the comparison is not vacuous
    with_bad = build_map(seq.scans, poses, include=np.ones(len(seq), bool))
    assert not np.array_equal(with_bad.logodds, ref_map.logodds)


def test_no_odometry_fallbacks(seq):
    bad = {5, 6}
    det = AlignmentDetector()
    still = ScanGuard(det, ScriptedMatcher(seq.reference, bad), initial_pose=seq.reference[0])
    d_still = run(still, seq, odometry=False)
    for i in bad:
        assert d_still[i].odometry_increment is None
        np.testing.assert_allclose(d_still[i].pose, d_still[i - 1].pose)
    cv = ScanGuard(
        det,
        ScriptedMatcher(seq.reference, bad),
        GuardConfig(motion_prior="constant_velocity"),
        initial_pose=seq.reference[0],
    )
    d_cv = run(cv, seq, odometry=False)
    true_inc = relative(seq.reference[:-1], seq.reference[1:])
    # step 5 repeats step 4's (accepted) increment, step 6 repeats that again
    np.testing.assert_allclose(d_cv[5].applied_increment, true_inc[3], atol=1e-12)
    np.testing.assert_allclose(d_cv[6].applied_increment, true_inc[3], atol=1e-12)


def test_policies_and_thresholds(seq):
    def guard(policy, cnn=None, base=None, **kw):
        return ScanGuard(
            cnn,
            ScriptedMatcher(seq.reference, {3}),
            GuardConfig(policy=policy, **kw),
            baseline=base,
            initial_pose=seq.reference[0],
        )

    with pytest.raises(ConfigError, match="needs a CNN"):
        guard("cnn")
    with pytest.raises(ConfigError, match="needs a baseline"):
        guard("both", cnn=AlignmentDetector())
    # baseline that always flags: everything after the first scan is rejected
    d = run(guard("baseline", base=ConstantJudge(0.9)), seq)
    assert {x.reason for x in d[1:]} == {"rejected_baseline"}
    # threshold override from the config wins over the judge's own
    d = run(guard("baseline", base=ConstantJudge(0.9), baseline_threshold=0.95), seq)
    assert all(x.accepted for x in d)
    # both: the CNN alone catches step 3; a flagging baseline makes it "rejected_both"
    d = run(guard("both", cnn=AlignmentDetector(), base=ConstantJudge(0.0)), seq)
    assert [x.index for x in d if not x.accepted] == [3]
    d = run(guard("both", cnn=AlignmentDetector(), base=ConstantJudge(1.0)), seq)
    assert d[3].reason == "rejected_both" and d[2].reason == "rejected_baseline"
    # score_all computes the unused detector too, without letting it decide
    det = AlignmentDetector()
    d = run(guard("baseline", cnn=det, base=ConstantJudge(0.0), score_all=True), seq)
    assert det.calls == len(seq) - 1
    assert d[3].accepted and d[3].fault_probability == 1.0
    assert np.isnan(run(guard("none"), seq)[3].fault_probability)


def test_odometry_initial_guess_uses_sensor_frame(seq):
    off = (0.3, 0.1, 0.2)
    m = ScriptedMatcher(seq.reference, set(), offset=off)
    g = ScanGuard(
        AlignmentDetector(),
        m,
        GuardConfig(odometry_initial_guess=True),
        laser_offset=off,
        initial_pose=seq.reference[0],
    )
    run(g, seq)
    odo_inc = relative(seq.odometry[:-1], seq.odometry[1:])
    off_a = np.asarray(off)
    expected = relative(compose(seq.odometry[:-1], off_a), compose(seq.odometry[1:], off_a))
    np.testing.assert_allclose(np.array(m.initials), expected, atol=1e-12)
    assert not np.allclose(expected, odo_inc)
    m2 = ScriptedMatcher(seq.reference, set())
    run(ScanGuard(AlignmentDetector(), m2, initial_pose=seq.reference[0]), seq)
    assert all(x is None for x in m2.initials)  # the paper: identity start


def test_laser_offset_fused_pose_is_robot_pose(seq):
    off = (0.3, 0.1, 0.2)
    g = ScanGuard(
        AlignmentDetector(),
        ScriptedMatcher(seq.reference, set(), offset=off),
        laser_offset=off,
        initial_pose=seq.reference[0],
    )
    d = run(g, seq)
    np.testing.assert_allclose(np.array([x.pose for x in d]), seq.reference, atol=1e-9)


def test_match_failures_fall_back(seq):
    class Failing(ScriptedMatcher):
        def __call__(self, source, target, initial=None):
            out = super().__call__(source, target, initial)
            if self.calls == 2:
                raise MatchingError("synthetic failure")
            if self.calls == 4:
                return Match(out.pose, ok=False)
            return out

    g = ScanGuard(AlignmentDetector(), Failing(seq.reference, set()), initial_pose=seq.reference[0])
    d = run(g, seq)
    assert [x.index for x in d if x.reason == "match_failed"] == [2, 4]
    assert g.n_failed == 2
    odo_inc = relative(seq.odometry[:-1], seq.odometry[1:])
    np.testing.assert_allclose(d[2].applied_increment, odo_inc[1], atol=1e-12)
    # too few points: an empty scan cannot be matched
    empty = seq.scans[0].with_ranges(np.full(seq.scans[0].n_beams, np.inf), stamp=99.0)
    g2 = ScanGuard(AlignmentDetector(), ScriptedMatcher(seq.reference, set()))
    g2.step(seq.scans[0])
    assert g2.step(empty).reason == "match_failed"


def test_guards_are_independent(seq):
    def make():
        return ScanGuard(
            AlignmentDetector(), ScriptedMatcher(seq.reference, {4}), initial_pose=seq.reference[0]
        )

    solo = run(make(), seq)
    a, b = make(), make()
    inter = []
    for i, scan in enumerate(seq.scans):
        inter.append(a.step(scan, seq.odometry[i]))
        b.step(scan, None)  # a different stream in the same process
    for x, y in zip(solo, inter, strict=True):
        assert x.accepted == y.accepted
        np.testing.assert_allclose(x.pose, y.pose)
    assert set(solo[1].timings) == {"match", "detect", "baseline", "map", "total"}
    assert solo[1].timings["total"] >= solo[1].timings["map"] >= 0.0


def test_skipped_scans_are_not_judged_but_become_the_previous_scan(seq):
    class PairMatcher:
        """Returns the true step between the two scans it is given (known by their points)."""

        def __init__(self) -> None:
            self.pairs: list[tuple[int, int]] = []
            self.ids = {id(s.points()): i for i, s in enumerate(seq.scans)}

        def __call__(self, source, target, initial=None):
            cur, prev = self.ids[id(source)], self.ids[id(target)]
            self.pairs.append((prev, cur))
            return Match(relative(seq.reference[prev], seq.reference[cur]))

    m = PairMatcher()
    det = AlignmentDetector()
    guard = ScanGuard(det, m, initial_pose=seq.reference[0])
    judge = [k % 3 == 0 for k in range(len(seq))]
    d = [guard.step(s, seq.odometry[k], judge=judge[k]) for k, s in enumerate(seq.scans)]
    judged = [k for k in range(1, len(seq)) if judge[k]]
    # the matcher and the detector ran on the judged scans only, each against the scan before
    assert m.pairs == [(k - 1, k) for k in judged]
    assert det.calls == len(judged)
    assert d[0].reason == "first"
    skipped = [k for k in range(1, len(seq)) if not judge[k]]
    assert [x.index for x in d if x.reason == "skipped"] == skipped
    assert guard.n_skipped == len(skipped) and guard.n_rejected == 0
    odo_inc = relative(seq.odometry[:-1], seq.odometry[1:])
    true_inc = relative(seq.reference[:-1], seq.reference[1:])
    for k in skipped:
        assert not d[k].accepted and d[k].match is None
        assert np.isnan(d[k].fault_probability) and np.isnan(d[k].baseline_score)
        assert np.isnan(d[k].match_increment).all()
        # the guard's own pose moves as on a reject: by odometry
        np.testing.assert_allclose(d[k].applied_increment, odo_inc[k - 1], atol=1e-12)
    for k in judged:
        assert d[k].accepted
        np.testing.assert_allclose(d[k].applied_increment, true_inc[k - 1], atol=1e-9)
    # judge=True everywhere is the plain loop
    plain = ScanGuard(AlignmentDetector(), ScriptedMatcher(seq.reference, set()))
    assert all(plain.step(s, None, judge=True).accepted for s in seq.scans)
    assert plain.n_skipped == 0


# --- classical baseline gate (the <backend>+baseline instance) ---------------------------------


class InjectingMatcher:
    """A `MatchResult` of the true step, wrong by ``BAD`` at ``bad`` steps; the ICP quality
    metrics follow the error (residual up, overlap down), as a real failed match's do."""

    def __init__(self, reference: np.ndarray, bad: set[int]) -> None:
        self.truth = relative(reference[:-1], reference[1:])
        self.bad = bad
        self.calls = 0

    def __call__(self, source, target, initial=None):
        from scanguard.matching.result import MatchResult

        i = self.calls
        self.calls += 1
        faulty = i + 1 in self.bad
        pose = compose(self.truth[i], BAD) if faulty else self.truth[i].copy()
        mag = 0.5 if faulty else 0.01 * (1 + i % 3)
        return MatchResult(
            pose=pose,
            iterations=4,
            converged=True,
            reason="converged",
            mean_residual=0.01 + mag,
            median_residual=0.01 + mag,
            inlier_ratio=max(0.0, 0.95 - mag),
            inlier_threshold=0.05,
            n_source=len(source),
            n_target=len(target),
            n_inliers=len(source),
        )


@pytest.fixture(scope="module")
def baseline_store(tmp_path_factory):
    """A two-sequence pair store (train + val) whose faults show in the residual."""
    from scanguard.dataset import label_sequence, write_sequence_file
    from scanguard.dataset.store import write_manifest
    from scanguard.pairs.labels import LabelConfig

    out = tmp_path_factory.mktemp("store")
    files = []
    for k, split in enumerate(["train", "val"]):
        rng = np.random.default_rng(60 + k)
        steps = np.column_stack(
            [rng.uniform(0.05, 0.1, 12), rng.uniform(-0.02, 0.02, 12), np.zeros(12)]
        )
        s = make_sequence(room_segments(), steps, start=(-1.0, -0.5, 0.1), seed=k)
        rec = label_sequence(
            s,
            environment="room",
            sequence=f"room_{k}",
            split=split,
            matcher=InjectingMatcher(s.reference, {2, 5, 9}),
            matcher_name="inject",
            initial_guess="identity",
            labels=LabelConfig(),
            gmapping=False,
        )
        write_sequence_file(out / f"room_{k}.h5", rec)
        files.append({"file": f"room_{k}.h5", "split": split})
    write_manifest(out, {"format": "scanguard-pairs", "sequences": files})
    return out


def test_baseline_fitted_on_store_gates_the_loop(seq, baseline_store):
    from scanguard.apps.run_baseline import fit_best_baseline
    from scanguard.slam.judge import BaselineJudge

    det, scores = fit_best_baseline(baseline_store, ["residual", "overlap"])
    assert set(scores) == {"residual", "overlap"} and scores[det.name] == 1.0
    judge = BaselineJudge(det, "test")
    bad = {4, 11, 17}
    guard = ScanGuard(
        None,
        InjectingMatcher(seq.reference, bad),
        GuardConfig(policy="baseline"),
        baseline=judge,
        initial_pose=seq.reference[0],
    )
    decisions = run(guard, seq)
    assert {d.index for d in decisions if not d.accepted} == bad
    assert all(decisions[i].reason == "rejected_baseline" for i in bad)
    odo_inc = relative(seq.odometry[:-1], seq.odometry[1:])
    for i in bad:
        np.testing.assert_allclose(decisions[i].applied_increment, odo_inc[i - 1], atol=1e-12)
    # the judge decides exactly as the detector's own predict() on the same features
    m = InjectingMatcher(seq.reference, {1})
    for k in range(3):
        match = m(np.zeros((5, 2)), np.zeros((5, 2)))
        feats = judge.pair_features(seq.scans[k], seq.scans[k + 1], match)
        flagged = judge.score(seq.scans[k], seq.scans[k + 1], match) >= judge.threshold
        assert flagged == bool(det.predict(feats)[0]) == (k == 0)


def test_gmapping_judge_uses_the_pair_geometry(seq):
    from scanguard.apps.run_baseline import GMAPPING_MIN_SCORE_FRACTION, gmapping_fallback_baseline
    from scanguard.matching.quality import gmapping_score
    from scanguard.matching.result import MatchResult
    from scanguard.slam.judge import BaselineJudge

    det = gmapping_fallback_baseline()
    assert det.threshold == pytest.approx(50.0 / 600.0) == GMAPPING_MIN_SCORE_FRACTION
    judge = BaselineJudge(det)
    prev, cur = seq.scans[3], seq.scans[4]
    true = relative(compose(seq.reference[3], seq.laser_offset), seq.reference[4])
    for pose, fault in ((true, False), (compose(true, np.array([2.5, -2.0, 1.3])), True)):
        # n_source is what the matcher got, so gmapping_score_norm = score / n_source as in training
        n = len(cur.points())
        match = MatchResult(pose, 3, True, "converged", 0.0, 0.0, 1.0, 0.05, n_source=n)
        norm = gmapping_score(prev, cur, pose, normalized=True)
        assert (norm < GMAPPING_MIN_SCORE_FRACTION) == fault
        assert (judge.score(prev, cur, match) >= judge.threshold) == fault


def test_resolve_baseline_sources(tmp_path, monkeypatch, baseline_store):
    import scanguard.apps.run_baseline as sr
    from scanguard.detect.baselines.registry import save_detector
    from scanguard.detect.baselines.threshold import ThresholdDetector

    monkeypatch.setattr(sr, "shipped_baseline_path", lambda matcher=None: tmp_path / "absent.json")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert sr.resolve_baseline("none") == (None, "none")
    judge, info = sr.resolve_baseline("auto", tmp_path / "no-dataset")
    assert judge is not None and "minimumScore" in info
    assert judge.detector.feature == "gmapping_score_norm"
    # a saved detector file
    det = ThresholdDetector("mean_residual", "high", name="res").fit(
        {"mean_residual": [0.01, 0.02, 0.4, 0.5]}, [0, 0, 1, 1]
    )
    path = save_detector(det, tmp_path / "res.json")
    judge, info = sr.resolve_baseline(str(path))
    assert judge is not None and judge.detector.threshold == pytest.approx(det.threshold)
    # auto with a dataset: fitted (then cached) best baseline; a shipped file wins
    judge, info = sr.resolve_baseline("auto", baseline_store)
    assert judge is not None and "fitted on the train split" in info
    assert len(list((tmp_path / "cache" / "scanguard").glob("baseline-*.json"))) == 2
    again, _ = sr.resolve_baseline("auto", baseline_store)
    assert again is not None and again.name == judge.name
    monkeypatch.setattr(sr, "shipped_baseline_path", lambda matcher=None: path)
    judge, info = sr.resolve_baseline("auto", baseline_store)
    assert judge is not None and judge.name == "res" and "shipped" in info
    with pytest.raises(ConfigError):
        sr.resolve_baseline("residual", tmp_path / "no-dataset")
    with pytest.raises(ConfigError):
        sr.resolve_baseline("no-such-thing")


def test_motion_prior_reads_the_old_fallback_key():
    cfg = GuardConfig.from_dict({"fallback": "constant_velocity"})
    assert cfg.motion_prior == "constant_velocity"
    assert GuardConfig.from_dict({"motion_prior": "constant_velocity"}) == cfg
