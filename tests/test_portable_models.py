"""Shipped and newly fitted classical models are stored version-free: no pickle, no sklearn.

The expected probabilities of the shipped models were recorded from the former pickled
sklearn estimators before the files were converted (`tests/data/make_model_fixture.py`).
"""

from __future__ import annotations

import base64
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scanguard.detect.baselines.convert import convert_file
from scanguard.detect.baselines.metrics_model import MetricsModelDetector, _single_thread
from scanguard.detect.baselines.portable import export_sklearn, model_from_dict
from scanguard.detect.baselines.registry import load_detector, save_detector
from scanguard.errors import ModelError
from scanguard.slam.graph.judges import (
    LearnedClosureJudge,
    load_closure_judge,
    save_closure_judge,
)

DATA = Path(__file__).parent / "data"
MODELS = Path(__file__).parents[1] / "src" / "scanguard" / "models"
SHIPPED = sorted(p.name for p in MODELS.glob("*.json"))

# Run in a fresh interpreter: sklearn cannot be imported, and anything that unpickles raises
# (pickle itself is imported by numpy, so it is disarmed rather than removed).
_NO_PICKLE = """
import json, pickle, sys
import numpy as np

def refuse(*a, **k):
    raise RuntimeError("pickle used")

def hook(event, args):
    if event == "pickle.find_class":
        raise RuntimeError("pickle used")

sys.addaudithook(hook)
pickle.loads = pickle.load = pickle.Unpickler = refuse
sys.modules["sklearn"] = None
from scanguard.detect.baselines.registry import load_detector
from scanguard.slam.graph.judges import load_closure_judge

fixture = np.load(sys.argv[1], allow_pickle=False)
out = {}
for path in sys.argv[2:]:
    name = path.rsplit("/", 1)[-1]
    x = fixture[name + ":x"]
    if name == "closure_judge.json":
        judge = load_closure_judge(path).learned
        p = judge.predict_proba({f: x[:, i] for i, f in enumerate(judge.features)})
    else:
        p = load_detector(path).predict_proba(x)
    out[name] = p.tolist()
assert "sklearn" not in sys.modules or sys.modules["sklearn"] is None
print(json.dumps(out))
"""


def _xy(n: int = 400, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Seeded features over several decades, with NaN, and labels tied to them."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 5)) * np.array([1.0, 10.0, 0.01, 1e3, 1.0])
    y = (x[:, 0] + x[:, 1] / 10 + rng.normal(scale=0.7, size=n) > 0).astype(np.int64)
    x[rng.random(x.shape) < 0.06] = np.nan
    return x, y


def test_shipped_models_load_without_pickle_or_sklearn() -> None:
    assert set(SHIPPED) == {
        "baseline.json",
        "baseline-icp.json",
        "baseline-plicp.json",
        "baseline-correlative.json",
        "closure_judge.json",
    }
    fixture = DATA / "shipped_model_probabilities.npz"
    args = [str(fixture), *(str(MODELS / n) for n in SHIPPED)]
    res = subprocess.run(
        [sys.executable, "-c", _NO_PICKLE, *args], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout.strip().splitlines()[-1])
    expected = np.load(fixture, allow_pickle=False)
    for name in SHIPPED:
        want = expected[name + ":proba"]
        assert len(want) == 96
        np.testing.assert_allclose(got[name], want, rtol=0, atol=1e-12)
        assert 0.05 < float(np.mean(want >= 0.5)) < 0.95  # the rows reach both classes
    for name in SHIPPED:
        assert "model_pickle" not in (MODELS / name).read_text()


def test_export_reproduces_sklearn_probabilities() -> None:
    x, y = _xy()
    xt, _ = _xy(300, seed=4)
    # the split thresholds themselves and one ulp either side must go the way sklearn sends them
    for kind in ("gbm", "logistic"):
        with _single_thread():
            est = MetricsModelDetector(kind=kind)._build().fit(x, y)
        model = export_sklearn(est)
        again = model_from_dict(json.loads(json.dumps(model.to_dict())))
        probe = xt
        if kind == "gbm":
            splits = [n for (p,) in est._predictors for n in p.nodes if not n["is_leaf"]]
            t = [float(n["num_threshold"]) for n in splits]
            f = [int(n["feature_idx"]) for n in splits]
            probe = np.repeat(xt[:1], 3 * len(t), axis=0)
            for i, (ti, fi) in enumerate(zip(t, f, strict=True)):
                for k, v in enumerate((ti, np.nextafter(ti, np.inf), np.nextafter(ti, -np.inf))):
                    probe[3 * i + k, fi] = v
            probe = np.concatenate([xt, probe])
        want = est.predict_proba(probe)[:, 1]
        for m in (model, again):
            np.testing.assert_allclose(m.predict_proba(probe), want, rtol=0, atol=1e-12)
        assert 0.1 < float(np.mean(want[: len(xt)] >= 0.5)) < 0.9


@pytest.mark.parametrize("kind", ["gbm", "logistic"])
def test_fitted_detector_saves_plain_arrays(tmp_path: Path, kind: str) -> None:
    x, y = _xy()
    xs, ys = _xy(200, seed=5)
    det = MetricsModelDetector(kind=kind, name=f"m-{kind}").fit(x, y, select=(xs, ys))
    path = save_detector(det, tmp_path / "det.json")
    data = json.loads(path.read_text())
    assert "model_pickle" not in data
    assert data["model"]["kind"] == ("hist-gbm" if kind == "gbm" else "logistic")
    back = load_detector(path)
    assert isinstance(back, MetricsModelDetector)
    assert back.threshold == det.threshold
    np.testing.assert_array_equal(back.predict_proba(xs), det.predict_proba(xs))
    np.testing.assert_array_equal(back.predict(xs), det.predict(xs))
    # the fitted detector predicts with the very numbers sklearn would give
    with _single_thread():
        est = MetricsModelDetector(kind=kind)._build().fit(det._matrix(x), y)
    np.testing.assert_allclose(
        det.predict_proba(xs), est.predict_proba(det._matrix(xs))[:, 1], rtol=0, atol=1e-12
    )


def test_closure_judge_saves_plain_arrays(tmp_path: Path) -> None:
    x, y = _xy()
    names = [f"c{i}" for i in range(x.shape[1])]
    table = {n: x[:, i] for i, n in enumerate(names)}
    det = MetricsModelDetector(names, name="closure-gbm").fit(table, y)
    path = save_closure_judge(tmp_path / "judge.json", LearnedClosureJudge(det, 0.4))
    assert "model_pickle" not in path.read_text()
    back = load_closure_judge(path).learned
    np.testing.assert_array_equal(back.predict_proba(table), det.predict_proba(table))
    assert back.threshold == 0.4


def _legacy_file(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """A detector file of the former format, with the sklearn estimator pickled inside."""
    x, y = _xy()
    det = MetricsModelDetector(kind="gbm", name="old").fit(x, y)
    with _single_thread():
        est = MetricsModelDetector(kind="gbm")._build().fit(x, y)
    data = det.to_dict()
    del data["model"]
    data["model_pickle"] = base64.b64encode(pickle.dumps(est)).decode("ascii")
    data["sklearn_version"] = "1.9.1"
    path = tmp_path / "old.json"
    path.write_text(json.dumps(data))
    return path, x, est.predict_proba(x)[:, 1]


def test_pickled_file_refused_and_converted(tmp_path: Path) -> None:
    old, x, want = _legacy_file(tmp_path)
    with pytest.raises(ModelError) as err:
        load_detector(old)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{old}: ")
    assert "python -m scanguard.detect.baselines.convert" in msg
    judge = tmp_path / "old_judge.json"
    entry = json.loads(old.read_text())
    judge.write_text(
        json.dumps(
            {
                "format": "scanguard-closure-judge",
                "version": 1,
                "learned": {"threshold": 0.5, "model": entry},
            }
        )
    )
    with pytest.raises(
        ModelError, match=r"old_judge\.json: .*scanguard\.detect\.baselines\.convert"
    ):
        load_closure_judge(judge)

    new = tmp_path / "new.json"
    assert convert_file(old, new) == 1
    np.testing.assert_allclose(load_detector(new).predict_proba(x), want, rtol=0, atol=1e-12)
    assert convert_file(judge, judge) == 1  # in place, nested entry
    assert load_closure_judge(judge).learned.model.model is not None
    with pytest.raises(ModelError, match="no pickled model"):
        convert_file(new, tmp_path / "again.json")


@pytest.mark.parametrize(
    "model",
    [
        [1],
        {"kind": "forest"},
        {"kind": "hist-gbm", "n_features": 1, "baseline": 0.0, "trees": "x"},
        {  # a child pointing back at its parent: a cycle
            "kind": "hist-gbm",
            "n_features": 1,
            "baseline": 0.0,
            "trees": [
                {
                    "left": [1, 0],
                    "right": [1, -1],
                    "feature": [0, 0],
                    "threshold": [0.5, 0.0],
                    "missing_left": [1, 0],
                    "value": [0.0, 1.0],
                }
            ],
        },
        {"kind": "logistic", "n_features": 2, "coef": [1.0], "intercept": 0.0},
    ],
)
def test_malformed_model_entry_is_a_model_error(tmp_path: Path, model: object) -> None:
    path = tmp_path / "bad.json"
    path.write_text(
        json.dumps(
            {"type": "metrics-model", "name": "b", "kind": "gbm", "features": ["a"], "model": model}
        )
    )
    with pytest.raises(ModelError) as err:
        load_detector(path)
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)
