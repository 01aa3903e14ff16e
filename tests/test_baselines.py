from __future__ import annotations

import json

import numpy as np
import pytest

from scanguard.detect.baselines.base import DEFAULT_METRICS_FEATURES, FeatureDetector
from scanguard.detect.baselines.metrics_model import MetricsModelDetector
from scanguard.detect.baselines.registry import (
    BASELINES,
    load_detector,
    make_baseline,
    save_detector,
)
from scanguard.detect.baselines.threshold import ThresholdDetector
from scanguard.detect.features import with_derived_features
from scanguard.errors import ConfigError, ModelError
from scanguard.geometry import relative
from scanguard.matching.quality import gmapping_features, gmapping_score
from tests.helpers import make_scan, room_segments

# --- gmapping_score ---------------------------------------------------------------------------


@pytest.mark.parametrize("p1", [(0.3, 0.1, 0.1), (-1.0, 0.5, -0.4)])
def test_gmapping_score_peaks_at_true_alignment(p1):
    seg = room_segments()
    prev, cur = make_scan(seg, (0.0, 0.0, 0.0)), make_scan(seg, p1)
    true = relative(np.zeros(3), np.asarray(p1))
    at_truth = gmapping_features(prev, cur, true)
    assert at_truth["gmapping_score_norm"] > 0.94
    assert at_truth["gmapping_score"] == pytest.approx(
        at_truth["gmapping_score_norm"] * len(cur.points())
    )
    offsets = [(0.1, 0, 0), (0.2, 0, 0), (0, 0.1, 0), (0, 0, 0.05), (0, 0, 0.1), (0.3, -0.2, 0.1)]
    scores = [gmapping_score(prev, cur, true + np.array(o), normalized=True) for o in offsets]
    assert max(scores) < at_truth["gmapping_score_norm"] - 0.15
    # a larger misalignment along the same direction scores lower
    x_scores = [gmapping_score(prev, cur, true + np.array([d, 0, 0])) for d in (0, 0.1, 0.2)]
    assert x_scores[0] > x_scores[1] > x_scores[2]
    rot_scores = [gmapping_score(prev, cur, true + np.array([0, 0, d])) for d in (0, 0.05, 0.1)]
    assert rot_scores[0] > rot_scores[1] > rot_scores[2]


def test_gmapping_score_known_values_and_free_cell_rule():
    # A wall at x = 1.01 seen from the origin; the current scan is the same points.
    y = np.linspace(-0.5, 0.5, 21)
    wall = np.stack([np.full_like(y, 1.01), y], axis=1)
    f = gmapping_features(wall, wall, (0.0, 0.0, 0.0))
    assert f["gmapping_matched"] == 1.0
    # Each endpoint matches the mean of its own 5 cm cell: d^2 <= 0.025^2 * 2.
    assert f["gmapping_score_norm"] > np.exp(-2 * 0.025**2 / 0.05)
    # A second layer of previous points sqrt(2) cells in front of the wall (x = 0.935, cell 18)
    # makes every wall cell fail GMapping's "free space in front" test: nothing matches.
    double = np.concatenate([wall, wall - [0.075, 0.0]])
    g = gmapping_features(double, wall, (0.0, 0.0, 0.0))
    assert g["gmapping_matched"] == 0.0 and g["gmapping_score"] == 0.0
    # The same wall seen from behind (sensor at x = 2) has free space at x ~ 1.08: matches.
    h = gmapping_features(wall, wall - [2.0, 0.0], (2.0, 0.0, 0.0))
    assert h["gmapping_matched"] == 1.0
    # far outside the kernel window: no match at all
    assert gmapping_score(wall, wall, (0.5, 0.0, 0.0)) == 0.0
    # kernel_size widens the search window: a 7 cm shift is matched with kernel 2 only
    shifted = gmapping_features(wall, wall, (0.0, 0.07, 0.0), kernel_size=0)
    wide = gmapping_features(wall, wall, (0.0, 0.07, 0.0), kernel_size=2)
    assert wide["gmapping_score"] > shifted["gmapping_score"]


def test_gmapping_score_empty_and_hash_fallback(monkeypatch):
    import scanguard.matching.quality as baselines

    seg = room_segments()
    prev, cur = make_scan(seg, (0, 0, 0)), make_scan(seg, (0.2, 0.1, 0.05))
    assert gmapping_score(np.empty((0, 2)), cur, (0, 0, 0)) == 0.0
    assert gmapping_score(prev, np.empty((0, 2)), (0, 0, 0), normalized=True) == 0.0
    pose = relative(np.zeros(3), np.array([0.2, 0.1, 0.05])) + np.array([0.03, -0.02, 0.01])
    dense = gmapping_features(prev, cur, pose)
    monkeypatch.setattr(baselines, "_DENSE_CELLS", 0)
    assert gmapping_features(prev, cur, pose) == pytest.approx(dense, rel=1e-12)
    with pytest.raises(ConfigError, match="sigma"):
        gmapping_score(prev, cur, (0, 0, 0), sigma=0.0)
    # max_range drops endpoints beyond it (the room's walls are all farther than 0.5 m)
    assert gmapping_score(prev, cur, pose, max_range=0.5) == 0.0
    assert gmapping_score(prev, cur, pose, max_range=30.0) == pytest.approx(dense["gmapping_score"])


def _assert_same_features(a: dict[str, float], b: dict[str, float]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-9, abs=1e-12), k


@pytest.mark.parametrize("dense_cells", [None, 0])
def test_gmapping_kernel_matches_numpy_reference(monkeypatch, dense_cells):
    """The compiled kernel gives the reference's values (dense table and hash table paths)."""
    import scanguard.matching.quality as baselines

    if dense_cells is not None:
        monkeypatch.setattr(baselines, "_DENSE_CELLS", dense_cells)
    ref = baselines._gmapping_features_numpy
    rng = np.random.default_rng(7)
    seg = room_segments()
    n_checked = n_matched = 0
    for trial in range(12):
        p0 = rng.uniform([-1.0, -1.0, -np.pi], [1.0, 1.0, np.pi])
        p1 = p0 + rng.normal(0.0, [0.15, 0.15, 0.1])
        prev, cur = make_scan(seg, p0), make_scan(seg, p1)
        true = relative(p0, p1)
        for pose in (true, true + rng.normal(0.0, [0.05, 0.05, 0.03])):
            kw = {"kernel_size": trial % 3, "sigma": (0.05, 0.01, 0.2)[trial % 3]}
            if trial % 4 == 3:
                kw["max_range"] = 3.0
            got = gmapping_features(prev, cur, pose, **kw)
            _assert_same_features(got, ref(prev, cur, pose, **kw))
            n_checked += 1
            n_matched += got["gmapping_matched"] > 0.5
    assert n_checked == 24 and n_matched >= 10  # real matches, not only zeros


def test_gmapping_kernel_random_clouds_and_edge_cases():
    """Random clouds (shared and empty cells, coarse and fine grids), NaN, empty inputs."""
    import scanguard.matching.quality as baselines

    ref = baselines._gmapping_features_numpy
    rng = np.random.default_rng(11)
    for _ in range(40):
        a = rng.normal(0.0, rng.uniform(0.2, 5.0), size=(int(rng.integers(1, 400)), 2))
        b = a[rng.permutation(len(a))] + rng.normal(0.0, 0.03, size=a.shape)
        b = b[: int(rng.integers(1, len(b) + 1))]
        kw = {
            "pose": rng.normal(0.0, [0.05, 0.05, 0.05]),
            "resolution": float(rng.choice([0.02, 0.05, 0.2])),
            "free_cell_ratio": float(rng.uniform(0.0, 3.0)),
            "kernel_size": int(rng.integers(0, 3)),
            "max_range": None if rng.random() < 0.5 else float(rng.uniform(0.5, 6.0)),
        }
        pose = kw.pop("pose")
        _assert_same_features(gmapping_features(a, b, pose, **kw), ref(a, b, pose, **kw))
    # non-finite points are dropped, a single point works, empty inputs give zeros
    a = rng.normal(0.0, 2.0, size=(50, 2))
    a[3] = np.nan
    a[7, 1] = np.inf
    _assert_same_features(gmapping_features(a, a, np.zeros(3)), ref(a, a, np.zeros(3)))
    assert gmapping_features(a[:1], a[:1], np.zeros(3))["gmapping_matched"] == 1.0
    zero = {"gmapping_score": 0.0, "gmapping_score_norm": 0.0, "gmapping_matched": 0.0}
    for p, c in ((np.empty((0, 2)), a), (a, np.empty((0, 2))), ([], [])):
        assert gmapping_features(p, c, np.zeros(3)) == zero == ref(p, c, np.zeros(3))
    # max_range removing every point of one scan
    assert gmapping_features(a, a, np.zeros(3), max_range=1e-6) == zero


# --- detectors --------------------------------------------------------------------------------


def _clusters(rng: np.random.Generator, n0: int = 300, n1: int = 100):
    labels = np.r_[np.zeros(n0, int), np.ones(n1, int)]
    residual = np.r_[rng.normal(0.02, 0.003, n0), rng.normal(0.10, 0.01, n1)]
    inlier = np.r_[rng.uniform(0.8, 1.0, n0), rng.uniform(0.2, 0.5, n1)]
    return {"mean_residual": residual, "inlier_ratio": inlier}, labels


def test_threshold_lands_between_separated_clusters():
    feats, y = _clusters(np.random.default_rng(0))
    high = ThresholdDetector("mean_residual", "high").fit(feats, y)
    gap_lo = feats["mean_residual"][y == 0].max()
    gap_hi = feats["mean_residual"][y == 1].min()
    assert gap_lo < high.threshold < gap_hi
    assert high.threshold == pytest.approx((gap_lo + gap_hi) / 2)
    assert high.train_score == 1.0
    np.testing.assert_array_equal(high.predict(feats), y)
    low = ThresholdDetector("inlier_ratio", "low").fit(feats, y)
    assert feats["inlier_ratio"][y == 1].max() < low.threshold < feats["inlier_ratio"][y == 0].min()
    np.testing.assert_array_equal(low.predict(feats), y)
    # raw arrays work too (1-D = the feature itself)
    arr = ThresholdDetector("x", "high").fit(feats["mean_residual"], y)
    assert arr.threshold == pytest.approx(high.threshold)


def test_threshold_maximises_balanced_accuracy_on_overlapping_classes():
    rng = np.random.default_rng(1)
    y = np.r_[np.zeros(900, int), np.ones(100, int)]
    x = np.r_[rng.normal(0.0, 1.0, 900), rng.normal(1.5, 1.0, 100)]
    det = ThresholdDetector("f", "high").fit({"f": x}, y)

    def bal(t: float) -> float:
        pred = x > t
        return 0.5 * (pred[y == 1].mean() + (~pred[y == 0]).mean())

    grid = np.linspace(-3, 4, 2001)
    assert bal(det.threshold) >= max(bal(t) for t in grid) - 1e-12
    assert det.train_score == pytest.approx(bal(det.threshold))
    # plain accuracy with 9:1 imbalance puts the threshold much higher (fewer fault calls)
    acc = ThresholdDetector("f", "high", criterion="accuracy").fit({"f": x}, y)
    assert acc.threshold > det.threshold + 0.5


def test_threshold_proba_orientation_nan_and_ambiguous():
    from sklearn.metrics import roc_auc_score

    rng = np.random.default_rng(2)
    feats, y = _clusters(rng)
    feats["inlier_ratio"] = feats["inlier_ratio"] + rng.normal(0, 0.15, len(y))
    det = ThresholdDetector("inlier_ratio", "low").fit(feats, y)
    proba = det.predict_proba(feats)
    assert ((proba > 0.5) == (det.predict(feats) == 1)).all()
    assert ((proba > 0) & (proba < 1)).all()
    # same ranking as the raw feature (low = fault): identical ROC AUC
    assert roc_auc_score(y, proba) == pytest.approx(roc_auc_score(y, -feats["inlier_ratio"]))
    assert roc_auc_score(y, proba) == pytest.approx(roc_auc_score(y, det.score(feats)))
    # NaN counts as a fault
    nan = {"inlier_ratio": np.array([np.nan, 1.0])}
    np.testing.assert_array_equal(det.predict(nan), [1, 0])
    assert det.predict_proba(nan)[0] == 1.0
    # ambiguous (-1) rows do not influence the threshold
    extra = {"inlier_ratio": np.r_[feats["inlier_ratio"], np.full(500, 0.95)]}
    det2 = ThresholdDetector("inlier_ratio", "low").fit(extra, np.r_[y, np.full(500, -1)])
    assert det2.threshold == det.threshold


def test_detector_errors():
    det = ThresholdDetector("mean_residual", "high")
    with pytest.raises(ModelError, match="not fitted"):
        det.predict({"mean_residual": np.zeros(3)})
    with pytest.raises(ModelError, match="both normal"):
        det.fit({"mean_residual": np.zeros(3)}, [0, 0, -1])
    with pytest.raises(ModelError, match="missing feature"):
        det.fit({"other": np.zeros(3)}, [0, 1, 0])
    with pytest.raises(ModelError, match="labels"):
        det.fit({"mean_residual": np.zeros(3)}, [0, 1])
    with pytest.raises(ConfigError, match="direction"):
        ThresholdDetector("x", "up")  # type: ignore[arg-type]


def _combo_data(rng: np.random.Generator, n: int):
    """Faults need a high residual AND a low inlier ratio: each alone is a weak cue."""
    residual = rng.uniform(0, 1, n)
    inlier = rng.uniform(0, 1, n)
    y = ((residual > 0.5) & (inlier < 0.5)).astype(int)
    feats = {
        "mean_residual": residual,
        "inlier_ratio": inlier,
        "eig_min": rng.uniform(0, 1, n),  # noise feature
        "condition_number": np.where(rng.random(n) < 0.05, np.inf, rng.uniform(1, 1e6, n)),
        "gmapping_score": rng.uniform(0, 1000, n),
        "n_source": np.full(n, 1000.0),
    }
    return feats, y


@pytest.mark.parametrize("kind", ["gbm", "logistic"])
def test_metrics_model_beats_single_thresholds(kind):
    rng = np.random.default_rng(3)
    train, ytr = _combo_data(rng, 1500)
    test, yte = _combo_data(rng, 1000)

    def bal(pred: np.ndarray) -> float:
        return 0.5 * (pred[yte == 1].mean() + (1 - pred[yte == 0]).mean())

    model = MetricsModelDetector(kind=kind).fit(train, ytr)
    assert model.features == [
        f for f in DEFAULT_METRICS_FEATURES if f in with_derived_features(train)
    ]
    assert "gmapping_score_norm" in model.features
    best_single = max(
        bal(ThresholdDetector(f, d).fit(train, ytr).predict(test))
        for f, d in [("mean_residual", "high"), ("inlier_ratio", "low")]
    )
    ours = bal(model.predict(test))
    assert ours > (0.97 if kind == "gbm" else 0.85)
    assert ours > best_single + 0.05
    proba = model.predict_proba(test)
    assert proba.shape == (1000,) and ((proba >= 0) & (proba <= 1)).all()


def test_save_load_roundtrip(tmp_path):
    rng = np.random.default_rng(4)
    feats, y = _combo_data(rng, 400)
    fitted: list[FeatureDetector] = [
        ThresholdDetector("mean_residual", "high", name="residual").fit(feats, y),
        MetricsModelDetector(kind="gbm").fit(feats, y),
        MetricsModelDetector(["mean_residual", "inlier_ratio"], kind="logistic").fit(feats, y),
    ]
    for i, det in enumerate(fitted):
        path = save_detector(det, tmp_path / f"d{i}.json")
        json.loads(path.read_text())  # valid JSON
        back = load_detector(path)
        assert type(back) is type(det) and back.name == det.name
        assert back.threshold == det.threshold
        np.testing.assert_array_equal(back.predict_proba(feats), det.predict_proba(feats))
    with pytest.raises(ModelError, match="not found"):
        load_detector(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ModelError, match="bad"):
        load_detector(tmp_path / "bad.json")


def test_registry_and_derived_features():
    assert set(BASELINES) == {"residual", "overlap", "degeneracy", "gmapping", "metrics-model"}
    for name in BASELINES:
        det = make_baseline(name)
        assert isinstance(det, FeatureDetector) and det.name == name
    with pytest.raises(ConfigError, match="known: degeneracy"):
        make_baseline("magic")
    d = with_derived_features(
        {"gmapping_score": [50.0, 10.0], "n_source": [100, 0], "eig_min": [8.0], "n_inliers": [4]}
    )
    np.testing.assert_allclose(d["gmapping_score_norm"], [0.5, 0.0])
    np.testing.assert_allclose(d["eig_min_per_inlier"], [2.0])
    # the gmapping baseline works from the stored raw score via the derived per-beam score
    y = np.r_[np.zeros(50, int), np.ones(50, int)]
    feats = {
        "gmapping_score": np.r_[np.full(50, 900.0), np.full(50, 300.0)],
        "n_source": 1000.0 * np.ones(100),
    }
    gm = make_baseline("gmapping").fit(feats, y)
    assert gm.threshold == pytest.approx(0.6)


def test_metrics_model_on_plain_arrays():
    rng = np.random.default_rng(5)
    feats, y = _combo_data(rng, 600)
    x = np.stack([feats["mean_residual"], feats["inlier_ratio"]], axis=1)
    model = MetricsModelDetector(kind="logistic").fit(x, y)
    assert model.features == ["f0", "f1"]
    # residual up = more fault, inlier ratio up = less fault
    coef = model.model.coef[0]  # type: ignore[union-attr]
    assert coef[0] > 0 > coef[1]
    with pytest.raises(ModelError, match="expected 2 feature column"):
        model.predict(x[:, :1])


# --- scale-free features and the CNN's threshold rule ----------------------------------------


def _all_metrics(rng: np.random.Generator, n: int, fault_share: float = 0.5):
    """Every stored metric (the derived per-beam / per-inlier ones included), faults known.

    Faults have a larger residual, a lower inlier ratio and a lower per-beam GMapping score;
    the scale-dependent columns are noise in the units of some sensor.
    """
    y = (rng.random(n) < fault_share).astype(int)
    f = y.astype(float)
    n_source = rng.integers(300, 400, n).astype(float)
    inlier = np.clip(rng.normal(0.9 - 0.3 * f, 0.12), 0, 1)
    eig_min = rng.uniform(10, 100, n)
    feats = {
        "iterations": rng.integers(3, 30, n).astype(float),
        "converged": (rng.random(n) < 0.95).astype(float),
        "mean_residual": np.abs(rng.normal(0.02 + 0.03 * f, 0.015)),
        "median_residual": np.abs(rng.normal(0.015 + 0.02 * f, 0.01)),
        "inlier_ratio": inlier,
        "eig_min": eig_min,
        "eig_mid": eig_min * 2,
        "eig_max": eig_min * 10,
        "condition_number": rng.uniform(5, 50, n),
        "n_source": n_source,
        "n_target": n_source + 5,
        "n_inliers": np.round(n_source * inlier),
        "translation": rng.uniform(0.05, 0.2, n),
        "rotation": rng.uniform(0.0, 0.1, n),
        "ok": np.ones(n),
        "gmapping_score": n_source * np.clip(rng.normal(0.8 - 0.3 * f, 0.15), 0, 1),
    }
    # the derived scale-free columns, as `store_features` delivers them
    return with_derived_features(feats), y


def test_default_features_are_scale_free_and_legacy_set_is_kept():
    from scanguard.detect.baselines.base import (
        LEGACY_METRICS_FEATURES,
        SCALE_DEPENDENT_METRICS_FEATURES,
        SCALE_FREE_METRICS_FEATURES,
    )
    from scanguard.detect.model import METRIC_FEATURES

    assert DEFAULT_METRICS_FEATURES == SCALE_FREE_METRICS_FEATURES
    assert set(METRIC_FEATURES) <= set(DEFAULT_METRICS_FEATURES)  # the hybrid CNN's, + more
    assert not set(DEFAULT_METRICS_FEATURES) & set(SCALE_DEPENDENT_METRICS_FEATURES)
    assert set(SCALE_DEPENDENT_METRICS_FEATURES) <= set(LEGACY_METRICS_FEATURES)
    assert len(LEGACY_METRICS_FEATURES) == 18 and "n_source" in LEGACY_METRICS_FEATURES
    for name in BASELINES:
        det = make_baseline(name)
        if isinstance(det, ThresholdDetector):
            assert det.feature in SCALE_FREE_METRICS_FEATURES, name
        else:
            assert isinstance(det, MetricsModelDetector) and det.features is None  # = default


def test_default_metrics_model_ignores_scale_dependent_columns():
    from scanguard.detect.baselines.base import SCALE_DEPENDENT_METRICS_FEATURES

    rng = np.random.default_rng(10)
    train, ytr = _all_metrics(rng, 400)
    test, _ = _all_metrics(rng, 200)
    model = MetricsModelDetector().fit(train, ytr)
    assert model.features == list(DEFAULT_METRICS_FEATURES)

    def scaled(feats):  # another sensor (10x the beams) and robot (10x the steps)
        return {k: v * 10 if k in SCALE_DEPENDENT_METRICS_FEATURES else v for k, v in feats.items()}

    proba = model.predict_proba(test)
    np.testing.assert_array_equal(model.predict_proba(scaled(test)), proba)
    # fitted on the scaled data it is the same model too
    other = MetricsModelDetector().fit(scaled(train), ytr)
    np.testing.assert_array_equal(other.predict_proba(test), proba)
    assert other.threshold == model.threshold
    # the legacy feature set does read them (and so does not transfer)
    from scanguard.detect.baselines.base import LEGACY_METRICS_FEATURES

    legacy = MetricsModelDetector(LEGACY_METRICS_FEATURES).fit(train, ytr)
    assert not np.array_equal(legacy.predict_proba(scaled(test)), legacy.predict_proba(test))


def test_metrics_model_threshold_is_choose_threshold_on_the_selection_set(tmp_path):
    from scanguard.scoring import choose_threshold

    rng = np.random.default_rng(11)
    train, ytr = _all_metrics(rng, 400)
    val, yval = _all_metrics(rng, 300, fault_share=0.2)
    yval[:10] = -1  # ambiguous pairs do not count
    model = MetricsModelDetector().fit(train, ytr, select=(val, yval))
    keep = yval >= 0
    want = choose_threshold(yval[keep], model.predict_proba(val)[keep])
    assert model.threshold == want and model.n_select == int(keep.sum())
    pred = model.predict(val)[keep]
    bal = 0.5 * (pred[yval[keep] == 1].mean() + (1 - pred[yval[keep] == 0]).mean())
    assert model.select_score == pytest.approx(bal)
    # the same model and threshold as a fit without selection plus select_threshold
    plain = MetricsModelDetector().fit(train, ytr)
    assert plain.select_threshold(val, yval) == want
    # the round trip keeps the selected threshold and its provenance
    back = load_detector(save_detector(model, tmp_path / "m.json"))
    assert isinstance(back, MetricsModelDetector)
    assert (back.threshold, back.select_score, back.n_select) == (
        want,
        model.select_score,
        model.n_select,
    )
    np.testing.assert_array_equal(back.predict(val), model.predict(val))
    with pytest.raises(ModelError, match="selection set"):
        model.select_threshold(val, np.zeros(len(yval), int))


def test_selection_threshold_moves_as_it_must():
    # fit set: separable residuals; the real robot's normal matches are noisier (up to 0.25)
    fit_x = np.r_[np.linspace(0.0, 0.1, 50), np.linspace(0.3, 0.5, 50)]
    fit_y = np.r_[np.zeros(50, int), np.ones(50, int)]
    sel_x = np.r_[np.linspace(0.0, 0.25, 90), np.linspace(0.27, 0.5, 10)]
    sel_y = np.r_[np.zeros(90, int), np.ones(10, int)]  # 9:1, unlike the 1:1 fit set
    fit_only = ThresholdDetector("mean_residual", "high").fit({"mean_residual": fit_x}, fit_y)
    assert fit_only.threshold == pytest.approx(0.2)  # centre of the fit set's gap
    det = ThresholdDetector("mean_residual", "high").fit(
        {"mean_residual": fit_x}, fit_y, select=({"mean_residual": sel_x}, sel_y)
    )
    assert det.threshold == pytest.approx(0.26)  # centre of the selection set's gap
    assert det.select_score == 1.0 and det.n_select == 100
    assert det.train_score == 1.0  # 0.26 still separates the fit set

    # Overlapping classes: balanced accuracy ignores the class balance, plain accuracy does not.
    rng = np.random.default_rng(12)
    xn, xf = rng.normal(0.0, 1.0, 200), rng.normal(1.5, 1.0, 200)
    balanced = ({"f": np.r_[xn, xf]}, np.r_[np.zeros(200, int), np.ones(200, int)])
    skewed = ({"f": np.r_[np.tile(xn, 9), xf]}, np.r_[np.zeros(1800, int), np.ones(200, int)])
    for crit in ("balanced_accuracy", "accuracy"):
        a = ThresholdDetector("f", "high", criterion=crit).fit(*balanced, select=balanced)
        b = ThresholdDetector("f", "high", criterion=crit).fit(*balanced, select=skewed)
        if crit == "balanced_accuracy":
            assert b.threshold == a.threshold
        else:  # 9x more normal pairs: fewer fault calls
            assert b.threshold > a.threshold + 0.5

    # the metrics model: the same, on its probability threshold
    feats, y = _all_metrics(rng, 600)
    val, yval = _all_metrics(rng, 300)
    model = MetricsModelDetector().fit(feats, y, select=(val, yval))
    normal = yval == 0
    rep = {k: np.r_[np.tile(v[normal], 9), v[~normal]] for k, v in val.items()}
    yrep = np.r_[np.zeros(9 * int(normal.sum()), int), np.ones(int((~normal).sum()), int)]
    assert MetricsModelDetector().fit(feats, y, select=(rep, yrep)).threshold == model.threshold
    # selection faults that look more normal (the model gives them lower probabilities):
    # the threshold goes down to keep catching them
    hard = dict(val)
    hard["mean_residual"] = np.where(yval == 1, val["mean_residual"] * 0.6, val["mean_residual"])
    hard["inlier_ratio"] = np.where(yval == 1, val["inlier_ratio"] + 0.15, val["inlier_ratio"])
    assert MetricsModelDetector().fit(feats, y, select=(hard, yval)).threshold < model.threshold


# --- fit_baselines (evaluate) and run on a small store ----------------------------------------


@pytest.fixture(scope="module")
def split_store(tmp_path_factory: pytest.TempPathFactory):
    """Train / val / test pairs whose faults show in the residual (val faults are 0.3 m off).

    Returns ``(store directory, {split: (max normal residual, min fault residual)})``.
    """
    from scanguard.dataset.store import write_manifest
    from tests.test_evaluate import write_injected_sequence

    out = tmp_path_factory.mktemp("splits")
    fault = {"train": 0.5, "val": 0.3, "test": 0.4}
    files = []
    for k, split in enumerate(fault):
        write_injected_sequence(out, k, 70 + k, split, "room", fault[split])
        files.append({"file": f"s{k}.h5", "split": split})
    write_manifest(out, {"format": "scanguard-pairs", "sequences": files})
    return out


def _gap(store, split: str) -> float:
    """Centre of the residual gap between the normal and fault pairs of ``split``."""
    idx = store.indices(split)
    r = np.asarray(store.records["mean_residual"])[idx]
    y = np.asarray(store.records["label"])[idx]
    assert (y == 0).any() and (y == 1).any() and r[y == 0].max() < r[y == 1].min()
    return float(r[y == 0].max() + r[y == 1].min()) / 2


def test_fit_baselines_chooses_thresholds_on_val(split_store, caplog):
    from scanguard.dataset import PairStore
    from scanguard.detect.evaluate import fit_baselines
    from scanguard.detect.features import store_features
    from scanguard.scoring import choose_threshold

    ps = PairStore.open(split_store)
    fitted = fit_baselines(ps, ["residual", "metrics-model"])
    val = ps.indices("val")
    assert fitted["residual"].threshold == pytest.approx(_gap(ps, "val"))
    assert fitted["residual"].n_select == len(val)
    assert _gap(ps, "val") < _gap(ps, "train") - 0.05  # a different answer than train's
    mm = fitted["metrics-model"]
    train = store_features(ps, ps.indices("train"))
    # the store's matcher fills no Hessian metrics: those all-NaN columns are left out
    assert mm.features == [
        f for f in DEFAULT_METRICS_FEATURES if f in train and np.isfinite(train[f]).any()
    ]
    assert "condition_number" not in mm.features and "mean_residual" in mm.features
    y_val = np.asarray(ps.records["label"])[val]
    assert mm.threshold == choose_threshold(y_val, mm.predict_proba(store_features(ps, val)))
    # no labelled pairs in the selection split: the fitting pairs, with a warning
    with caplog.at_level("WARNING", logger="scanguard.detect.evaluate"):
        fallback = fit_baselines(ps, ["residual"], select_splits=("nowhere",))
    assert "no labelled pairs of both classes" in caplog.text
    assert fallback["residual"].threshold == pytest.approx(_gap(ps, "train"))
    assert fallback["residual"].n_select == len(ps.indices("train"))


def test_run_and_evaluate_fit_the_same_baselines(split_store, tmp_path, monkeypatch):
    from scanguard.apps.run_baseline import cached_best_baseline, fit_best_baseline
    from scanguard.dataset import PairStore
    from scanguard.detect.evaluate import fit_baselines

    names = ["residual", "overlap", "metrics-model"]
    best, scores = fit_best_baseline(split_store, names)
    ours = fit_baselines(PairStore.open(split_store), names)
    assert set(scores) == set(ours)
    for name, det in ours.items():
        assert scores[name] == det.select_score
    assert type(best) is type(ours[best.name])
    assert best.threshold == ours[best.name].threshold
    assert best.to_dict() == ours[best.name].to_dict()
    # the cached variant (run's default) agrees too
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    for _ in range(2):  # fitted, then read back
        cached, cached_scores = cached_best_baseline(split_store)
        assert cached_scores == fit_best_baseline(split_store)[1]
        assert cached.threshold == fit_best_baseline(split_store)[0].threshold
