"""Images of stored pairs: augmentation, batch rendering into memory, PNG export."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.dataset.store import PairStore
from scanguard.detect.render import RenderStyle, render_pairs, save_png
from scanguard.geometry import compose
from scanguard.logging_utils import progress as progress_of
from scanguard.pairs.labels import AMBIGUOUS, LABEL_NAMES

log = logging.getLogger(__name__)


def augment_pair(
    previous: NDArray[np.floating],
    current: NDArray[np.floating],
    estimate: ArrayLike,
    rng: np.random.Generator,
    *,
    rotation_deg: float = 180.0,
    dropout: float = 0.1,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
    """Randomly rotate a whole pair about the previous sensor origin and drop points.

    The rotation ``a`` turns the previous points by ``R(a)`` and the estimate into
    ``(0, 0, a) ⊕ estimate``, so the relative alignment (and thus the label) is unchanged.

    Args:
        previous: Previous points ``(N, 2)``.
        current: Current points ``(M, 2)`` in the current sensor frame.
        estimate: Match estimate ``(3,)``.
        rng: Random generator.
        rotation_deg: Rotation drawn uniformly in ``[-rotation_deg, rotation_deg]``.
        dropout: Probability of dropping each point (independently per scan).

    Returns:
        ``(previous, current, estimate)`` augmented.
    """
    a = math.radians(rotation_deg) * rng.uniform(-1.0, 1.0) if rotation_deg > 0 else 0.0
    c, s = math.cos(a), math.sin(a)
    rot = np.array([[c, -s], [s, c]], dtype=np.float32)
    prev = np.asarray(previous, dtype=np.float32) @ rot.T
    cur = np.asarray(current, dtype=np.float32)
    est = compose(np.array([0.0, 0.0, a]), np.asarray(estimate, dtype=np.float64))
    if dropout > 0:
        prev = prev[rng.random(prev.shape[0]) >= dropout]
        cur = cur[rng.random(cur.shape[0]) >= dropout]
    return prev, cur, est


def render_all(
    store: PairStore,
    indices: Sequence[int] | NDArray[np.integer] | None,
    style: RenderStyle,
    *,
    batch_size: int = 256,
    progress: bool = False,
) -> NDArray[np.uint8]:
    """Render many stored pairs into one in-memory uint8 array (fast batched path).

    Args:
        store: The pair store.
        indices: Pair indices (None = every non-ambiguous pair).
        style: Render style.
        batch_size: Pairs per `render_pairs` call.
        progress: Show a progress bar.

    Returns:
        ``(N, H, W, C)`` uint8 images in the order of ``indices``.
    """
    idx = store.indices() if indices is None else np.asarray(indices, dtype=np.int64)
    out = np.empty((idx.size, *style.shape), dtype=np.uint8)
    starts = range(0, idx.size, batch_size)
    with progress_of(len(starts), "render", enabled=progress) as advance:
        for s in starts:
            _render_chunk(store, idx, s, batch_size, style, out)
            advance(1)
    return out


def _render_chunk(
    store: PairStore,
    idx: NDArray[np.int64],
    s: int,
    batch_size: int,
    style: RenderStyle,
    out: NDArray[np.uint8],
) -> None:
    """Render pairs ``idx[s : s + batch_size]`` into ``out`` at the same positions."""
    chunk = idx[s : s + batch_size]
    prevs, curs, ests = [], [], []
    for i in chunk.tolist():
        p, c, e = store.pair_points(int(i))
        prevs.append(p)
        curs.append(c)
        ests.append(e)
    poses = np.asarray(ests, dtype=np.float64).reshape(-1, 3)
    out[s : s + chunk.size] = render_pairs(prevs, curs, poses, style)


def export_png(
    store: PairStore,
    out_dir: str | Path,
    style: RenderStyle | None = None,
    *,
    per_class: int | None = None,
    environments: Sequence[str] | None = None,
    include_ambiguous: bool = False,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, dict[str, int]]:
    """Write pair images in the paper's layout ``<env>/normal/*.png``, ``<env>/fault/*.png``.

    Args:
        store: The pair store.
        out_dir: Destination root.
        style: Render style (default: the paper's 256x256 RGB).
        per_class: At most this many images per environment and class, drawn at random
            (seeded); None = all.
        environments: Only these environments (default: all).
        include_ambiguous: Also write ``<env>/ambiguous/``.
        seed: Seed of the subsampling.
        progress: Show a progress bar.

    Returns:
        ``{environment: {class: count}}`` written.
    """
    st = style or RenderStyle.paper()
    root = Path(out_dir)
    rng = np.random.default_rng(seed)
    r = store.records
    written: dict[str, dict[str, int]] = {}
    classes = [0, 1] + ([AMBIGUOUS] if include_ambiguous else [])
    for env in environments or store.environments:
        for lab in classes:
            sel = np.flatnonzero((r["environment"] == env) & (r["label"] == lab))
            if per_class is not None and sel.size > per_class:
                sel = np.sort(rng.choice(sel, size=per_class, replace=False))
            imgs = render_all(store, sel, st, progress=progress)
            name = LABEL_NAMES[lab]
            for i, img in zip(sel.tolist(), imgs, strict=True):
                fname = f"{r['sequence'][i]}_{int(r['pair'][i]):05d}.png"
                save_png(root / env / name / fname, img)
            written.setdefault(env, {})[name] = int(sel.size)
            log.info("%s/%s: %d images", env, name, sel.size)
    return written
