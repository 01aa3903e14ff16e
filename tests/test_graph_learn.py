"""The learned loop-closure judge: candidate features, fitting, files and gate wiring."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from scanguard.apps.closure_harvest import candidate_table
from scanguard.apps.closure_judge import fit_classical, fit_learned_judge
from scanguard.errors import ModelError, ScanGuardError
from scanguard.slam.graph import ClosureCandidate, ClosureJudgeConfig, ClosureRecord, ClosureVerdict
from scanguard.slam.graph.closure import FAULT, NORMAL, AcceptAll, ResponseTest
from scanguard.slam.graph.features import FEATURES, candidate_features
from scanguard.slam.graph.judges import (
    LEARNED_FEATURES,
    ClassicalClosureTest,
    LearnedClosureJudge,
    judge_for_gate,
    load_closure_judge,
    save_closure_judge,
)
from tests.helpers import make_scan


def _room() -> np.ndarray:
    """A 10 x 6 m room with a pillar and a notch (well constrained for ICP)."""
    return np.array(
        [
            (-5, -3, 5, -3),
            (5, -3, 5, 3),
            (5, 3, 1, 3),
            (1, 3, 1, 2),
            (1, 2, 0, 2),
            (0, 2, 0, 3),
            (0, 3, -5, 3),
            (-5, 3, -5, -3),
            (2, -1, 2.5, -1),
            (2.5, -1, 2.5, -0.5),
            (2.5, -0.5, 2, -0.5),
            (2, -0.5, 2, -1),
        ],
        dtype=np.float64,
    )


def _candidate(prior: tuple[float, float, float] = (0.3, 0.4, 0.05)) -> ClosureCandidate:
    world = _room()
    target = make_scan(world, (-1.0, 0.0, 0.0))
    source = make_scan(world, (-0.5, 0.2, 0.1))
    # true pose of the source sensor frame in the target's: (0.5, 0.2, 0.1)
    return ClosureCandidate(
        node=40,
        target_node=3,
        scan_index=400,
        target_scan_index=30,
        pose=np.array([0.5, 0.2, 0.1]),
        score=0.7,
        coarse_score=0.6,
        covariance=np.diag([0.02**2, 0.03**2, 0.01**2]),
        source=source,
        target=target,
        prior_pose=np.array(prior, dtype=np.float64),
        path_gap=20.0,
    )


def test_candidate_features_known_values() -> None:
    cand = _candidate(prior=(0.5, 0.2 + 0.4, 0.1 + 0.05))
    f = candidate_features(cand)
    assert set(FEATURES) <= set(f)
    assert f["response"] == pytest.approx(0.7)
    assert f["coarse_response"] == pytest.approx(0.6)
    assert f["std_xy"] == pytest.approx(0.03)
    assert f["std_theta"] == pytest.approx(0.01)
    # prior differs by 0.4 m (in the prior's frame rotated by 0.15 rad) and 0.05 rad
    assert f["disagreement_m"] == pytest.approx(0.4, abs=1e-9)
    assert f["disagreement_rad"] == pytest.approx(0.05, abs=1e-9)
    assert f["disagreement_m_per_m"] == pytest.approx(0.4 / 20.0, abs=1e-9)
    assert f["path_gap"] == pytest.approx(20.0)
    # the proposed pose is the true one: ICP stays, with small residuals and many inliers
    assert f["icp_shift_m"] < 0.02
    assert f["icp_shift_rad"] < 0.01
    assert f["icp_mean_residual"] < 0.02
    assert f["icp_inlier_ratio"] > 0.8
    table = candidate_table(
        [ClosureRecord(cand, ClosureVerdict(True, 0.7, "oracle"), label=NORMAL)]
    )
    assert table["label"].tolist() == [NORMAL]
    assert table["disagreement_m"][0] == pytest.approx(0.4, abs=1e-9)


def test_disagreement_in_standard_deviations_known_value() -> None:
    pose = np.array([0.5, 0.2, 0.1])
    c, s = math.cos(0.1), math.sin(0.1)
    # the prior lies 0.3 m behind the proposed pose along the node's own x axis
    prior = pose - np.array([0.3 * c, 0.3 * s, 0.0])
    cand = _candidate(prior=tuple(prior))
    assert cand.disagreement_sigmas != cand.disagreement_sigmas  # NaN: no prior covariance
    assert math.isnan(candidate_features(cand)["disagreement_sigmas"])
    cand.covariance = np.diag([0.03**2, 0.03**2, 0.01**2])  # isotropic: no frame to mind
    cand.prior_covariance = np.diag([0.04**2, 0.04**2, 0.02**2])
    # x variance 0.03^2 + 0.04^2 = 0.05^2: 0.3 m is six standard deviations
    assert cand.disagreement_sigmas == pytest.approx(6.0, abs=1e-9)
    assert candidate_features(cand)["disagreement_sigmas"] == pytest.approx(6.0, abs=1e-9)
    # a graph that knows it drifted (10x the standard deviation) takes it as 0.6 sigma
    cand.prior_covariance = np.diag([0.4**2 - 0.03**2, 0.4**2, 0.2**2])
    assert cand.disagreement_sigmas == pytest.approx(0.75, abs=1e-9)
    row = ClosureRecord(cand, ClosureVerdict(True, 0.1, "learned")).as_dict()
    assert row["disagreement_sigmas"] == pytest.approx(0.75, abs=1e-9)


def _synthetic(n: int, seed: int) -> dict[str, np.ndarray]:
    """Known labels: fault iff response < 0.55 or disagreement > 0.5 m (5 sigma)."""
    rng = np.random.default_rng(seed)
    t: dict[str, np.ndarray] = {f: rng.uniform(0.0, 1.0, n) for f in LEARNED_FEATURES}
    t["response"] = rng.uniform(0.3, 0.9, n)
    t["std_xy"] = rng.uniform(0.005, 0.04, n)
    t["std_theta"] = rng.uniform(0.001, 0.01, n)
    t["disagreement_m"] = rng.uniform(0.0, 1.0, n)
    t["disagreement_rad"] = rng.uniform(0.0, 0.1, n)
    # a clean gap around both thresholds
    t["response"] = np.where(np.abs(t["response"] - 0.55) < 0.02, 0.8, t["response"])
    t["disagreement_m"] = np.where(
        np.abs(t["disagreement_m"] - 0.5) < 0.02, 0.1, t["disagreement_m"]
    )
    low = t["response"] < 0.55
    t["disagreement_m"] = np.where(low, 0.45 * t["disagreement_m"], t["disagreement_m"])
    fault = low | (t["disagreement_m"] > 0.5)
    # the learned judge reads the disagreement in sigmas: a graph 10 cm unsure of itself
    t["disagreement_sigmas"] = t["disagreement_m"] / 0.1
    t["label"] = np.where(fault, FAULT, NORMAL).astype(np.float64)
    return t


def test_fit_classical_recovers_known_thresholds() -> None:
    t = _synthetic(400, 0)
    test = fit_classical(t)
    assert 0.5 <= test.min_response <= 0.57
    assert 0.48 <= test.max_disagreement_m <= 0.52
    low_faults = t["response"][t["response"] < 0.55]
    assert low_faults.max() < test.min_response < t["response"][t["response"] > 0.55].min()
    # irrelevant gates stay off (or never reject a training candidate)
    ok = test.passes(t)
    assert np.array_equal(ok, t["label"] == NORMAL)
    with pytest.raises(ModelError, match="fault"):
        fit_classical({**t, "label": np.zeros(400)})


def _fitted_judge() -> LearnedClosureJudge:
    t = _synthetic(240, 1)
    groups = np.repeat(np.arange(3), 80)
    return fit_learned_judge(t, groups, kinds=("logistic", "gbm"))


def test_learned_judge_save_load_round_trip(tmp_path: Path) -> None:
    judge = _fitted_judge()
    assert 0.0 < judge.threshold < 1.0
    assert judge.provenance["n_train"] == 240
    probe = _synthetic(50, 7)
    p = judge.predict_proba(probe)
    assert np.mean((p >= judge.threshold) == (probe["label"] == FAULT)) > 0.8
    classical = ClassicalClosureTest(0.5, 0.05, 0.02, 0.4, math.inf)
    path = save_closure_judge(
        tmp_path / "closure_judge.json", judge, classical, {"scenarios": ["x"]}
    )
    loaded = load_closure_judge(path)
    assert np.array_equal(loaded.learned.predict_proba(probe), p)
    assert loaded.learned.threshold == judge.threshold
    assert loaded.classical is not None
    assert loaded.classical.thresholds() == classical.thresholds()
    assert loaded.provenance == {"scenarios": ["x"]}
    cand = _candidate()
    assert loaded.learned.probability(cand) == judge.probability(cand)
    verdict = loaded.learned(cand)
    assert verdict.judge == "learned"


def test_judge_for_gate_uses_the_judge_file(tmp_path: Path) -> None:
    cfg = ClosureJudgeConfig()
    path = tmp_path / "closure_judge.json"
    classical = ClassicalClosureTest(0.5, 0.05, 0.02, 0.4)
    save_closure_judge(path, _fitted_judge(), classical)
    cnn = judge_for_gate("cnn", cfg, judge_file=path)
    assert isinstance(cnn, LearnedClosureJudge)
    assert cnn.name == "learned"
    base = judge_for_gate("baseline", cfg, judge_file=path)
    assert isinstance(base, ClassicalClosureTest)
    assert base.max_disagreement_m == pytest.approx(0.4)
    assert isinstance(judge_for_gate("none", cfg, judge_file=path), AcceptAll)
    # no file: the detector judge and the configured classical test
    absent = tmp_path / "absent.json"
    base = judge_for_gate("baseline", cfg, judge_file=absent)
    assert type(base) is ResponseTest
    with pytest.raises(ValueError, match="detector"):
        judge_for_gate("cnn", cfg, judge_file=absent)
    # the classical gate: the disagreement stops a closure that would move the graph 0.45 m
    cand = _candidate(prior=(0.5, 0.2 + 0.45, 0.1))
    assert not judge_for_gate("baseline", cfg, judge_file=path)(cand).accepted


def test_run_config_names_the_judge_file(tmp_path: Path) -> None:
    from scanguard.slam.config import RunConfig
    from scanguard.slam.registry import closure_judge_for

    path = tmp_path / "mine.json"
    save_closure_judge(path, _fitted_judge(), ClassicalClosureTest(0.5, 0.05, 0.02, 0.4))
    cfg = RunConfig.model_validate({"graph": {"closures": {"judge_file": str(path)}}})
    base = closure_judge_for(cfg, "baseline", None, np.zeros(3), None)
    assert isinstance(base, ClassicalClosureTest)
    assert base.max_disagreement_m == pytest.approx(0.4)
    assert isinstance(closure_judge_for(cfg, "cnn", None, np.zeros(3), None), LearnedClosureJudge)
    # a file that is not there: one line naming it, never another judge in silence
    cfg = RunConfig.model_validate(
        {"graph": {"closures": {"judge_file": str(tmp_path / "no.json")}}}
    )
    with pytest.raises(ModelError, match=r"no\.json: closure-judge file not found"):
        closure_judge_for(cfg, "cnn", None, np.zeros(3), None)
    # a file that is not a judge: one line naming it
    bad = tmp_path / "bad.json"
    bad.write_text("not json {")
    cfg = RunConfig.model_validate({"graph": {"closures": {"judge_file": str(bad)}}})
    with pytest.raises(ModelError, match=r"bad\.json"):
        closure_judge_for(cfg, "cnn", None, np.zeros(3), None)


@pytest.mark.parametrize(
    "content",
    [
        "not json {",
        json.dumps({"format": "something-else"}),
        json.dumps({"format": "scanguard-closure-judge", "version": 1, "learned": {}}),
    ],
)
def test_corrupt_judge_file_is_a_one_line_error(tmp_path: Path, content: str) -> None:
    path = tmp_path / "closure_judge.json"
    path.write_text(content)
    with pytest.raises(ScanGuardError) as info:
        judge_for_gate("cnn", ClosureJudgeConfig(), judge_file=path)
    msg = str(info.value)
    assert str(path) in msg
    assert "\n" not in msg
    with pytest.raises(ModelError, match="not found"):
        load_closure_judge(tmp_path / "missing.json")


def test_shipped_judge_file_loads_with_provenance() -> None:
    shipped = load_closure_judge()
    prov = shipped.provenance
    assert set(prov["train_seeds"]).isdisjoint(prov["test_seeds_held_out"])
    assert "choose_threshold" in prov["threshold_rule"]
    assert shipped.learned.threshold == pytest.approx(prov["threshold"])
    assert shipped.classical is not None
    assert set(shipped.learned.features) <= set(FEATURES)
    verdict = shipped.learned(_candidate())
    assert verdict.judge == "learned"
