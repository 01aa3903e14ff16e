"""The classical baseline gating a run's ``+baseline`` instance: shipped, fitted or GMapping's rule.

`resolve_baseline` turns a spec (``auto``, ``none``, a baseline name, a detector file) into a
`scanguard.slam.judge.BaselineJudge`; fitting reads a pair store (`scanguard.dataset`) and the
classifiers of `scanguard.detect`, which is why this lives with the apps and not in `slam`.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from scanguard.errors import ConfigError, InputError, ModelError
from scanguard.fsutil import atomic_write_text
from scanguard.pairs.labels import FAULT, NORMAL
from scanguard.safeload import load_json
from scanguard.slam.judge import BaselineJudge

logger = logging.getLogger(__name__)


#: GMapping's ``minimumScore`` convention (ROS wiki: "scores go up to 600+, try 50"), as a
#: fraction of the best possible score: the fallback threshold on ``gmapping_score_norm``.
GMAPPING_MIN_SCORE_FRACTION = 50.0 / 600.0
#: File name of a fitted baseline shipped next to the CNN weights (``scanguard/models/``).
SHIPPED_BASELINE_NAME = "baseline.json"


def shipped_baseline_path(matcher: str | None = None) -> Path:
    """Where a fitted baseline shipped with the package would be (per matcher, like the CNN).

    ``baseline.json`` goes with the default model (``icp-paper``); another matcher's, when one
    was fitted, is ``baseline-<matcher>.json``.
    """
    from importlib import resources

    folder = Path(str(resources.files("scanguard") / "models"))
    if matcher is not None and matcher != "icp-paper":
        own = folder / f"baseline-{matcher}.json"
        if own.is_file():
            return own
    return folder / SHIPPED_BASELINE_NAME


def default_dataset_dir() -> Path:
    """The paper dataset of a source checkout (``<repo>/data/paper``; may not exist)."""
    return Path(__file__).resolve().parents[2] / "data" / "paper"


def gmapping_fallback_baseline() -> Any:
    """GMapping's own rule: fault iff ``gmapping_score_norm < 50 / 600`` (no fitting)."""
    from scanguard.detect.baselines.threshold import ThresholdDetector

    return ThresholdDetector.from_dict(
        {
            "name": "gmapping (minimumScore 50/600)",
            "feature": "gmapping_score_norm",
            "direction": "low",
            "criterion": "balanced_accuracy",
            "threshold": GMAPPING_MIN_SCORE_FRACTION,
        }
    )


def fit_best_baseline(
    dataset: str | Path,
    names: list[str] | None = None,
    select_split: str = "val",
) -> tuple[Any, dict[str, float]]:
    """Fit classical baselines on a dataset's training split; keep the best on ``select_split``.

    The baselines are fitted by `scanguard.detect.evaluate.fit_baselines`, exactly as
    ``scanguard evaluate`` fits them: every baseline of
    `scanguard.detect.baselines.registry.BASELINES` (or ``names``) on the ``train`` pairs, with
    its threshold chosen by the CNN's rule (maximum balanced accuracy) on the ``select_split``
    pairs (the training pairs when that split has no labelled pairs of both classes).
    The best is the one with the highest balanced accuracy
    on the same selection pairs (ambiguous pairs excluded). Test pairs are never used.

    Args:
        dataset: A pair-store directory or file(s) accepted by `PairStore.open`.
        names: Baselines to try (default: all).
        select_split: Split the thresholds are chosen on and the best baseline is chosen by.

    Returns:
        ``(best fitted detector, {name: balanced accuracy on the selection split})``.

    Raises:
        ConfigError: The store has no labelled training pairs of both classes, or no baseline
            can be fitted on it.
    """
    from scanguard.dataset import PairStore
    from scanguard.detect.baselines.registry import BASELINES
    from scanguard.detect.evaluate import fit_baselines

    store = PairStore.open(dataset)
    train = store.indices("train")
    y_train = np.asarray(store.records["label"])[train].astype(np.int64)
    if len(train) == 0 or not ((y_train == FAULT).any() and (y_train == NORMAL).any()):
        raise ConfigError(f"{dataset}: no labelled training pairs of both classes to fit baselines")
    wanted = names or list(BASELINES)
    fitted = fit_baselines(store, wanted, ("train",), (select_split,), skip_unfittable=True)
    if not fitted:
        raise ConfigError(f"{dataset}: none of the baselines {wanted} could be fitted")
    scores: dict[str, float] = {}
    best: Any = None
    for name, det in fitted.items():
        # balanced accuracy at the chosen threshold on the selection pairs (every baseline of
        # BASELINES uses that criterion)
        scores[name] = float("nan") if det.select_score is None else float(det.select_score)
        if best is None or scores[name] > scores[best.name]:
            best = det
    logger.info(
        "best baseline on %s: %s (balanced accuracy %.3f)",
        select_split,
        best.name,
        scores[best.name],
    )
    return best, scores


#: Version of the baseline fitting rule, part of the cache key of `cached_best_baseline`
#: (2: scale-free features, thresholds chosen on the validation split by the CNN's rule;
#: 3: stored as plain arrays, so a cache file of the pickled format is never read).
BASELINE_FIT_VERSION = 3


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

    from scanguard.detect.baselines.registry import load_detector, save_detector

    data = Path(dataset)
    manifest = data / "manifest.json" if data.is_dir() else data
    try:
        digest = hashlib.sha1(manifest.read_bytes())
        digest.update(f"baseline-fit-v{BASELINE_FIT_VERSION}".encode())
        key = digest.hexdigest()[:16]
    except OSError:
        return fit_best_baseline(data)
    cache = baseline_cache_dir()
    det_path = cache / f"baseline-{key}.json"
    score_path = cache / f"baseline-{key}.scores.json"
    if det_path.is_file() and score_path.is_file():
        try:
            return load_detector(det_path), load_json(score_path, error=ModelError)
        except ModelError as exc:
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
    spec: str | None = "auto", dataset: str | Path | None = None, matcher: str | None = None
) -> tuple[BaselineJudge | None, str]:
    """The classical detector gating trajectory (d), and a sentence saying where it came from.

    Args:
        spec: ``"none"``/None (no trajectory (d)); a path to a detector JSON
            (`scanguard.detect.baselines.registry.save_detector`); a baseline name of
            `scanguard.detect.baselines.registry.BASELINES` (fitted on ``dataset``);
            ``"gmapping-default"`` (GMapping's ``minimumScore`` rule,
            `gmapping_fallback_baseline`); or ``"auto"``:
            the fitted baseline shipped in ``scanguard/models/baseline.json`` if present, else
            the best baseline fitted on the training split of ``dataset`` (default:
            `default_dataset_dir`) if it exists, else the GMapping rule.
        dataset: Pair store to fit on.
        matcher: The run's matcher: ``"auto"`` prefers the baseline shipped for it
            (`shipped_baseline_path`).

    Returns:
        ``(judge or None, description)``.

    Raises:
        ConfigError: A named baseline without a dataset to fit it on, or an unknown spec.
        ModelError: An unreadable detector file.
    """
    from scanguard.detect.baselines.registry import BASELINES, load_detector

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
    shipped = shipped_baseline_path(matcher)
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
