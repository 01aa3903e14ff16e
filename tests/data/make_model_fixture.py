"""Record what the shipped sklearn models answered before they were stored version-free.

Run once, from the repository root, on the OLD (pickled) model files:
``python tests/data/make_model_fixture.py`` (or give the old files' folder as argument, e.g.
one extracted with ``git show``). It unpickles each model (trusted, shipped files), builds a
seeded feature matrix per model that hits its split thresholds exactly, one ulp either side,
NaN and values in between, and writes the matrix and sklearn's fault probabilities to
``tests/data/shipped_model_probabilities.npz``. ``tests/test_portable_models.py`` checks that
the converted files give the same probabilities without sklearn or pickle.

A closure judge fitted after the conversion (session 21: the judge that reads the drift in
sigmas) was never pickled: ``python tests/data/make_model_fixture.py --closure-judge CACHE``
refits its sklearn estimator from the harvest cache it was trained on (deterministic), checks
that it exports to the shipped model exactly, and records that estimator's answers in place of
the file's old entries.
"""

from __future__ import annotations

import base64
import json
import pickle
import sys
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
MODELS = HERE.parents[1] / "src" / "scanguard" / "models"
NAMES = (
    "baseline.json",
    "baseline-icp.json",
    "baseline-plicp.json",
    "baseline-correlative.json",
    "closure_judge.json",
)
ROWS = 96


def _entry(data: dict[str, Any]) -> dict[str, Any]:
    return data["learned"]["model"] if "learned" in data else data


def _matrix(model: Any, n_features: int, rng: np.random.Generator) -> np.ndarray:
    """Columns drawn from the model's own thresholds (exact, +-1 ulp), ranges and NaN."""
    thresholds: list[list[float]] = [[] for _ in range(n_features)]
    for (predictor,) in model._predictors:
        for node in predictor.nodes:
            if not node["is_leaf"]:
                thresholds[int(node["feature_idx"])].append(float(node["num_threshold"]))
    x = np.empty((ROWS, n_features))
    for j, ts in enumerate(thresholds):
        t = np.array(ts or [0.0, 1.0])
        choice = rng.integers(0, 5, ROWS)
        pick = rng.choice(t, ROWS)
        lo, hi = t.min(), t.max()
        span = max(hi - lo, 1e-9)
        col = np.where(choice == 0, pick, rng.uniform(lo - span, hi + span, ROWS))
        col = np.where(choice == 1, np.nextafter(pick, np.inf), col)
        col = np.where(choice == 2, np.nextafter(pick, -np.inf), col)
        col = np.where(rng.random(ROWS) < 0.05, np.nan, col)
        x[:, j] = col
    return x


def main(folder: Path = MODELS) -> None:
    rng = np.random.default_rng(20240523)
    out: dict[str, np.ndarray] = {}
    for name in NAMES:
        entry = _entry(json.loads((folder / name).read_text()))
        model = pickle.loads(base64.b64decode(entry["model_pickle"]))
        x = _matrix(model, len(entry["features"]), rng)
        # what MetricsModelDetector.predict_proba did: +-inf -> NaN, then sklearn
        proba = model.predict_proba(np.where(np.isfinite(x), x, np.nan))[:, 1]
        out[f"{name}:x"] = x
        out[f"{name}:proba"] = np.asarray(proba, dtype=np.float64)
    np.savez_compressed(HERE / "shipped_model_probabilities.npz", **out)  # type: ignore[arg-type]


def closure_judge(cache: Path) -> None:
    """Replace the closure judge's entries with a refitted sklearn estimator's answers."""
    from scanguard.apps.closure_harvest import labelled, load_table, save_table, select
    from scanguard.detect.baselines.metrics_model import _single_thread
    from scanguard.detect.baselines.portable import export_sklearn
    from scanguard.slam.graph.judges import load_closure_judge

    shipped = load_closure_judge(MODELS / "closure_judge.json")
    detector = shipped.learned.model
    prov = shipped.provenance
    table = labelled(load_table(cache))
    table = select(table, np.isin(table["seed"], prov["train_seeds"]))
    table = select(table, np.isin(table["scenario"], prov["scenarios"]))
    x = detector._matrix({f: table[f] for f in detector.features})
    y = np.asarray(table["label"]).astype(np.int64)
    with _single_thread():
        model = detector._build().fit(x, y)
    if export_sklearn(model).to_dict() != detector.model.to_dict():
        raise SystemExit("the refitted estimator does not export to the shipped closure judge")
    rng = np.random.default_rng(20261205)
    grid = _matrix(model, len(detector.features), rng)
    proba = model.predict_proba(np.where(np.isfinite(grid), grid, np.nan))[:, 1]
    path = HERE / "shipped_model_probabilities.npz"
    with np.load(path, allow_pickle=False) as data:
        out = {k: np.asarray(data[k]) for k in data.files}
    out["closure_judge.json:x"] = grid
    out["closure_judge.json:proba"] = np.asarray(proba, dtype=np.float64)
    save_table(path, out)  # the project's atomic .npz writer


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--closure-judge":
        closure_judge(Path(sys.argv[2]))
    else:
        main(Path(sys.argv[1]) if len(sys.argv) > 1 else MODELS)
