"""Convert a detector or closure-judge file of the former pickled format, once, by hand.

    python -m scanguard.detect.baselines.convert OLD.json NEW.json

Older scanguard versions stored the fitted sklearn model of a `MetricsModelDetector` pickled
(base64) in the JSON (``model_pickle``), in a detector file (``save_detector``) or in a
closure-judge file (``save_closure_judge``). Loading no longer unpickles; this converter does,
once: it finds every ``model_pickle`` entry anywhere in the file, unpickles it (pickle runs
code: trusted files only, with a scikit-learn able to read it), copies it into the version-free
form (`scanguard.detect.baselines.portable.export_sklearn`), checks on a seeded matrix that hits
every split threshold that the copy gives the estimator's probabilities (to 1e-12), and writes
the file with a ``model`` entry instead. Nothing else in the file changes.
"""

from __future__ import annotations

import base64
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scanguard.detect.baselines.portable import PortableModel, export_sklearn
from scanguard.errors import ModelError, ScanGuardError
from scanguard.fsutil import atomic_write_text

log = logging.getLogger(__name__)

TOLERANCE = 1e-12
"""Largest difference in probability between the estimator and its copy that is accepted."""


def check_matrix(estimator: Any, n_rows: int = 512, seed: int = 0) -> np.ndarray:
    """A seeded ``(n_rows, n_features)`` matrix for comparing an estimator with its copy.

    For trees, each column mixes the feature's split thresholds (exactly and one ulp either
    side) with values around them; otherwise standard normal values spread over decades. About
    5 % are NaN, and a few +-inf.
    """
    rng = np.random.default_rng(seed)
    n = int(estimator.n_features_in_)
    x = rng.normal(size=(n_rows, n)) * 10.0 ** rng.integers(-3, 4, size=(n_rows, n))
    for predictor, *_ in getattr(estimator, "_predictors", []):
        nodes = predictor.nodes[~predictor.nodes["is_leaf"].astype(bool)]
        for node in nodes:
            rows = rng.random(n_rows) < 2.0 / max(len(nodes), 1)
            t = float(node["num_threshold"])
            j = int(node["feature_idx"])
            x[rows, j] = rng.choice([t, np.nextafter(t, np.inf), np.nextafter(t, -np.inf)])
    x[rng.random(x.shape) < 0.05] = np.nan
    x[rng.random(x.shape) < 0.005] = np.inf
    x[rng.random(x.shape) < 0.005] = -np.inf
    return x


def convert_estimator(estimator: Any) -> PortableModel:
    """`export_sklearn`, checked against the estimator's own ``predict_proba``.

    Raises:
        ModelError: Not exportable, or the copy's probabilities differ by more than
            `TOLERANCE`.
    """
    model = export_sklearn(estimator)
    x = check_matrix(estimator)
    if type(estimator).__name__ != "HistGradientBoostingClassifier":
        x = np.nan_to_num(x, nan=np.nan, posinf=1e6, neginf=-1e6)  # inf breaks the scaler
    want = np.asarray(estimator.predict_proba(x)[:, 1], dtype=np.float64)
    got = model.predict_proba(x)
    diff = float(np.max(np.abs(want - got)))
    if not diff <= TOLERANCE:
        raise ModelError(f"the converted model differs from the estimator by {diff:.3g}")
    return model


def _convert_tree(node: Any) -> int:
    """Replace every ``model_pickle`` in a JSON tree in place; return how many."""
    import pickle  # only here: loading a detector never imports it for this module

    count = 0
    if isinstance(node, dict):
        blob = node.pop("model_pickle", None)
        if blob is not None:
            estimator = pickle.loads(base64.b64decode(blob))
            node.pop("sklearn_version", None)
            node["model"] = convert_estimator(estimator).to_dict()
            count += 1
        for value in node.values():
            count += _convert_tree(value)
    elif isinstance(node, list):
        for value in node:
            count += _convert_tree(value)
    return count


def convert_file(old: str | Path, new: str | Path) -> int:
    """Write ``new``: ``old`` with every pickled model converted; return how many were.

    ``new`` may be ``old`` (written atomically after the conversion succeeded).

    Raises:
        ModelError: Not a JSON file, no pickled model in it, or a model that cannot be
            converted exactly (the message names the file).
    """
    src = Path(old)
    try:
        data = json.loads(src.read_text())
        count = _convert_tree(data)
    except (OSError, ValueError) as exc:
        raise ModelError(f"{src}: cannot convert ({exc})") from None
    except ModelError as exc:
        raise ModelError(f"{src}: {exc}") from None
    if count == 0:
        raise ModelError(f"{src}: no pickled model in it (already converted?)")
    atomic_write_text(Path(new), json.dumps(data, indent=1))
    return count


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m scanguard.detect.baselines.convert OLD NEW``; 0 on success, 1 on error."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 2:
        log.error("usage: python -m scanguard.detect.baselines.convert OLD.json NEW.json")
        return 2
    try:
        count = convert_file(args[0], args[1])
    except ScanGuardError as exc:
        log.error("error: %s", exc)
        return 1
    log.info("%s: %d model(s) converted, written to %s", args[0], count, args[1])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
