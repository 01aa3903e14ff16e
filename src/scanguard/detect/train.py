"""Training of the fault-detection CNN: seeded, reproducible, with best-epoch selection.

Images are rendered once (uint8, ``(N, H, W, C)``) and kept in memory; each epoch visits the
training images in an order drawn from a seeded generator, so two runs with the same config
and data give the same weights (``torch.use_deterministic_algorithms`` is not forced because
some CPU kernels lack deterministic variants; on the CPU the results are bit-identical in
practice). The epoch with the best validation accuracy (ties: lower validation loss) is kept,
and training stops early after ``patience`` epochs without improvement.

Outputs (all written atomically into ``out_dir``): ``model.pt`` (checkpoint with config,
render style, label thresholds, operating threshold and weights), ``config.yaml`` (resolved
config), ``history.json`` and ``curves.png`` (loss / accuracy per epoch, paper Figure 10).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike
from torch.nn.parallel import DistributedDataParallel

from scanguard.config import save_config
from scanguard.dataset.store import PairStore
from scanguard.detect.checkpoint import make_checkpoint, save_checkpoint
from scanguard.detect.distributed import (
    broadcast_floats,
    dist_rank_world,
    init_distributed,
    local_world,
)
from scanguard.detect.features import store_features
from scanguard.detect.images import render_all
from scanguard.detect.model import (
    FaultCNN,
    ModelConfig,
    build_model,
    count_parameters,
    metric_inputs,
)
from scanguard.detect.render import RenderStyle
from scanguard.detect.train_config import ImageSet, TrainConfig, TrainResult
from scanguard.detect.train_epoch import (
    DivergedError,
    make_schedule,
    non_finite_weights,
    run_epoch,
    validate,
    with_hidden_odometry,
)
from scanguard.errors import ConfigError, InputError
from scanguard.fsutil import atomic_write_text, save_figure
from scanguard.pairs.odometry import OdometryNoise
from scanguard.pairs.profile import PROFILE_FEATURES
from scanguard.scoring import metric_threshold

log = logging.getLogger(__name__)


def train_images(
    config: TrainConfig,
    train: ImageSet,
    val: ImageSet,
    out_dir: str | Path | None = None,
    *,
    label_thresholds: dict[str, Any] | None = None,
    data_info: dict[str, Any] | None = None,
    matchers: Sequence[str] | None = None,
) -> TrainResult:
    """Train on rendered images and keep the best validation epoch.

    Args:
        config: Training settings (resolved here if needed).
        train: Training images; ambiguous labels (-1) are dropped.
        val: Validation images (by sequence, disjoint from ``train``); may be empty, in which
            case the last epoch is kept and the threshold is 0.5.
        out_dir: Folder for ``model.pt``, ``config.yaml``, ``history.json``, ``curves.png``;
            ``None`` writes nothing.
        label_thresholds: The dataset's labelling rule, stored in the checkpoint.
        data_info: Free-form description of the data (stored in the checkpoint).
        matchers: Names of the matchers whose matches the images show, stored in the
            checkpoint (`FaultDetector.check_matcher`); ``None`` stores none (the detector
            then assumes ``icp-paper``, as for older checkpoints).

    Returns:
        The checkpoint, the trained model and the history.

    Raises:
        ConfigError: The image size or channels do not match the model, no training data,
            or training diverged (NaN or infinite loss or weights): nothing is written then.
    """
    cfg = config.resolved()
    assert cfg.model is not None and cfg.style is not None
    train, val = _usable_data(cfg, train, val)
    m = cfg.model
    rank, world = dist_rank_world()
    if rank != 0:
        out_dir = None  # rank 0 writes the checkpoint and the metrics, once
    where = f"{out_dir}: " if out_dir is not None else ""
    prev_threads = torch.get_num_threads()
    # the config's threads are per machine: processes on one machine share them
    torch.set_num_threads(max(1, cfg.threads // local_world()) if world > 1 else cfg.threads)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    try:
        model, step_model = _new_model(cfg, train, rank, world)
        history, best_epoch = _fit(model, step_model, cfg, train, val, gen, where)
        threshold, val_metrics = _operating_threshold(model, cfg, val, rank)
    finally:
        torch.set_num_threads(prev_threads)
    _check_trained(model, threshold, where)
    checkpoint = make_checkpoint(
        model,
        style=cfg.style,
        threshold=threshold,
        train_config=cfg.model_dump(mode="json"),
        label_thresholds=label_thresholds or {},
        matchers=matchers,
        odometry_noise=_odometry_noise_block(m),
        info={
            "best_epoch": best_epoch,
            "epochs_run": len(history),
            "n_train": len(train),
            "n_val": len(val),
            **({"processes": world} if world > 1 else {}),
            **val_metrics,
            **(data_info or {}),
        },
        history=history,
    )
    out_path = None
    if out_dir is not None:
        out_path = Path(out_dir)
        _write_outputs(cfg, checkpoint, history, best_epoch, out_path)
    return TrainResult(checkpoint=checkpoint, model=model, history=history, out_dir=out_path)


def _usable_data(cfg: TrainConfig, train: ImageSet, val: ImageSet) -> tuple[ImageSet, ImageSet]:
    """The labelled pairs of both sets, checked against the model (and subsampled)."""
    assert cfg.model is not None
    train = train.subset(train.labels >= 0)
    val = val.subset(val.labels >= 0)
    if len(train) == 0:
        raise ConfigError("training set is empty (no pair labelled normal or fault)")
    _, h, w, c = train.images.shape
    m = cfg.model
    if (h, w, c) != (m.input_size, m.input_size, m.in_channels):
        raise ConfigError(
            f"images are {h}x{w}x{c} but model {m.preset!r} expects "
            f"{m.input_size}x{m.input_size}x{m.in_channels}"
        )
    if m.metrics:
        for name, d in (("training", train), ("validation", val)):
            if d.metrics is None or d.metrics.shape[1] != len(m.metrics):
                raise ConfigError(
                    f"{name} data: model {m.preset!r} needs the metrics {m.metrics} next to "
                    "the images"
                )
    else:
        train.metrics = val.metrics = None
    if cfg.max_train is not None and len(train) > cfg.max_train:
        rng = np.random.default_rng(cfg.seed)
        train = train.subset(np.sort(rng.choice(len(train), cfg.max_train, replace=False)))
    return train, val


def _new_model(cfg: TrainConfig, train: ImageSet, rank: int, world: int) -> tuple[FaultCNN, Any]:
    """The initial network (metric scaling fitted on ``train``) and the module that steps.

    The stepping module is the network itself, or its DistributedDataParallel wrapper in a
    process group.
    """
    assert cfg.model is not None
    model = build_model(cfg.model)
    if train.metrics is not None:
        scaled = with_hidden_odometry(train.metrics, model, cfg)
        model.set_metric_scaling(scaled.mean(axis=0), scaled.std(axis=0))
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    step_model: Any = model
    if world > 1:
        step_model = DistributedDataParallel(model)  # rank 0's initial weights
        # dropout: every rank its own masks (the same seed would repeat one mask per share)
        torch.manual_seed(cfg.seed + 7919 * rank)
    return model, step_model


def _fit(
    model: FaultCNN,
    step_model: Any,
    cfg: TrainConfig,
    train: ImageSet,
    val: ImageSet,
    gen: torch.Generator,
    where: str,
) -> tuple[list[dict[str, float]], int]:
    """Run the epochs, keep the best validation epoch's weights; returns (history, best epoch).

    Raises:
        ConfigError: The loss became NaN or infinite.
    """
    assert cfg.model is not None
    rank = dist_rank_world()[0]
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = make_schedule(opt, cfg, -(-len(train) // cfg.batch_size))
    log.info(
        "training %s (%d parameters) on %d images (%d fault), validating on %d",
        cfg.model.preset,
        count_parameters(model),
        len(train),
        int(train.labels.sum()),
        len(val),
    )
    history: list[dict[str, float]] = []
    best_key: tuple[float, float] | None = None
    best_state: dict[str, torch.Tensor] | None = None
    best_epoch, stale = 0, 0
    for epoch in range(1, cfg.epochs + 1):
        try:
            tl, ta, ips = run_epoch(
                step_model, train, cfg, opt, gen, f"epoch {epoch}/{cfg.epochs}", sched
            )
        except DivergedError as exc:
            raise ConfigError(
                f"{where}training diverged: the loss is {exc.loss} in epoch {epoch} "
                f"(lr {cfg.lr:g}); no model was saved - lower lr"
            ) from None
        vl, va = tl, ta
        if len(val):
            if rank == 0:
                vl, va, _ = validate(model, val, cfg.channels_last)
            # one decision for every rank: rank 0's validation
            vl, va = broadcast_floats([vl, va])
        _record_epoch(history, epoch, tl, ta, vl, va, ips)
        key = (va, -vl)
        if best_key is None or key > best_key:
            best_key, best_epoch, stale = key, epoch, 0
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        else:
            stale += 1
            if cfg.patience and stale >= cfg.patience:
                log.info("early stop after epoch %d (best %d)", epoch, best_epoch)
                break
    assert best_state is not None
    model.load_state_dict(best_state)
    model.eval()
    return history, best_epoch


def _record_epoch(
    history: list[dict[str, float]],
    epoch: int,
    tl: float,
    ta: float,
    vl: float,
    va: float,
    ips: float,
) -> None:
    """Append one epoch's metrics to ``history`` and log them."""
    history.append(
        {
            "epoch": epoch,
            "train_loss": tl,
            "train_accuracy": ta,
            "val_loss": vl,
            "val_accuracy": va,
            "images_per_s": ips,
        }
    )
    log.info(
        "epoch %d: train loss %.4f acc %.4f | val loss %.4f acc %.4f | %.0f img/s",
        epoch,
        tl,
        ta,
        vl,
        va,
        ips,
    )


def _operating_threshold(
    model: FaultCNN, cfg: TrainConfig, val: ImageSet, rank: int
) -> tuple[float, dict[str, float]]:
    """The operating threshold chosen on ``val`` (0.5 without one) and the validation metrics."""
    threshold = 0.5
    val_metrics: dict[str, float] = {}
    if len(val):
        acc_t = vl = va = 0.0
        if rank == 0:
            vl, va, vp = validate(model, val, cfg.channels_last)
            threshold = metric_threshold(val.labels, vp, cfg.threshold_metric)
            acc_t = float(np.mean((vp >= threshold) == (val.labels == 1)))
        vl, va, threshold, acc_t = broadcast_floats([vl, va, threshold, acc_t])
        val_metrics = {
            "val_loss": vl,
            "val_accuracy_at_0.5": va,
            "val_accuracy_at_threshold": acc_t,
        }
    return threshold, val_metrics


def _check_trained(model: FaultCNN, threshold: float, where: str) -> None:
    """Refuse a model with non-finite weights or a threshold that is not a probability."""
    bad = non_finite_weights(model)
    if bad:
        raise ConfigError(
            f"{where}training produced non-finite weights ({', '.join(bad[:3])}"
            f"{', ...' if len(bad) > 3 else ''}); no model was saved - lower lr"
        )
    if not 0.0 <= threshold <= 1.0:
        raise ConfigError(
            f"{where}the validation split gave the operating threshold {threshold}; "
            "no model was saved"
        )


def _write_outputs(
    cfg: TrainConfig,
    checkpoint: dict[str, Any],
    history: list[dict[str, float]],
    best_epoch: int,
    out_path: Path,
) -> None:
    """Write ``model.pt``, ``config.yaml``, ``history.json`` and ``curves.png``."""
    assert cfg.model is not None
    out_path.mkdir(parents=True, exist_ok=True)
    save_checkpoint(checkpoint, out_path / "model.pt")
    save_config(cfg, out_path)
    atomic_write_text(out_path / "history.json", json.dumps(history, indent=2))
    plot_history(
        history, out_path / "curves.png", title=f"{cfg.model.preset} (best epoch {best_epoch})"
    )


def _odometry_noise_block(model: ModelConfig) -> dict[str, Any] | None:
    # the features were computed with the default noise model (`store_features`)
    if "has_odometry" not in model.metrics:
        return None
    return OdometryNoise().model_dump(mode="json")


def plot_history(history: list[dict[str, float]], path: str | Path, title: str = "") -> Path:
    """Loss and accuracy per epoch for train and validation (paper Figure 10) as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [h["epoch"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key in zip(axes, ["loss", "accuracy"], strict=True):
        ax.plot(ep, [h[f"train_{key}"] for h in history], "o-", label="train")
        ax.plot(ep, [h[f"val_{key}"] for h in history], "s-", label="validation")
        ax.set_xlabel("epoch")
        ax.set_ylabel(key)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    p = save_figure(fig, Path(path), dpi=100)
    return p


def load_store_images(
    store: str | Path | Any,
    style: dict[str, Any],
    *,
    splits: list[str] | None = None,
    environments: list[str] | None = None,
    exclude_environments: list[str] | None = None,
    include_ambiguous: bool = False,
    chunk: int = 512,
    metrics: list[str] | None = None,
) -> tuple[ImageSet, dict[str, Any]]:
    """Render the selected pairs of a `scanguard.dataset.PairStore` into memory.

    Args:
        store: A `PairStore` or anything `PairStore.open` accepts (build folder, ``.h5``).
        style: Render style fields.
        splits: Keep only these splits (``None``: all).
        environments: Keep only these environments (``None``: all).
        exclude_environments: Drop these environments.
        include_ambiguous: Keep pairs labelled -1.
        chunk: Pairs rendered per call (bounds the temporary memory).
        metrics: Also read these ICP metrics (`scanguard.detect.model.metric_inputs`) for a hybrid
            model.

    Returns:
        The images and the store's labelling rule (label thresholds of its first file).

    Raises:
        InputError: The store cannot be opened.
    """
    if not isinstance(store, PairStore):
        p = Path(store)
        if not p.exists():
            raise InputError(p, "pair store not found")
        store = PairStore.open(p)
    idx = store.indices(splits, environment=environments, include_ambiguous=include_ambiguous)
    rec = store.records
    env = np.asarray(rec["environment"]).astype(str)
    if exclude_environments:
        idx = idx[~np.isin(env[idx], exclude_environments)]
    rs = RenderStyle(**style)
    images = render_all(store, idx, rs, batch_size=chunk, progress=len(idx) > 0)
    try:
        label_rule = store.label_config(0).model_dump(mode="json") if store.files else {}
    except Exception:  # a store without label metadata still trains; the rule is just unknown
        label_rule = {}
    metric_arr = None
    if metrics:
        profile = any(n in PROFILE_FEATURES for n in metrics)
        metric_arr = metric_inputs(store_features(store, idx, profile=profile), metrics)
    data = ImageSet(
        images,
        np.asarray(rec["label"], dtype=np.int64)[idx],
        env[idx],
        np.asarray(rec["sequence"]).astype(str)[idx],
        idx.astype(np.int64),
        metric_arr,
    )
    return data, label_rule


def train(config: TrainConfig, store: Any, out_dir: str | Path) -> TrainResult:
    """Train on a pair store: ``train_split`` for fitting, ``val_split`` for selection.

    Args:
        config: Training settings.
        store: A `scanguard.dataset.PairStore` or what `PairStore.open` accepts (build
            folder(s), ``.h5`` file(s)).
        out_dir: Output folder (created).

    Under ``torchrun`` (``WORLD_SIZE`` > 1) every process joins one process group
    (`init_distributed`) and trains with DistributedDataParallel: each global batch of
    ``batch_size`` images is split over the ranks, gradients are averaged, so the same
    config file gives the same training as one process. ``threads`` is shared by the
    processes of one machine. Only rank 0 writes ``out_dir``.

    Returns:
        The training result; the checkpoint is in ``out_dir/model.pt``.

    Raises:
        ConfigError: The store's build is unfinished (``complete: false``) and
            ``allow_incomplete`` is off, or training failed (see `train_images`).
    """
    cfg = config.resolved()
    assert cfg.style is not None
    init_distributed()  # under torchrun: one process group, rank 0 writes

    ps = store if isinstance(store, PairStore) else PairStore.open(store)
    if ps.incomplete and not cfg.allow_incomplete:
        path, why = ps.incomplete[0]
        raise ConfigError(
            f"{path}: incomplete dataset build ({why}); finish it by running the same "
            "`dataset build` command again, or set allow_incomplete: true to train anyway"
        )
    envs, excl = cfg.environments, cfg.exclude_environments
    assert cfg.model is not None
    names = list(cfg.model.metrics) or None
    tr, label_thresholds = load_store_images(
        ps,
        cfg.style,
        splits=cfg.train_split,
        environments=envs,
        exclude_environments=excl,
        metrics=names,
    )
    va, _ = load_store_images(
        ps,
        cfg.style,
        splits=cfg.val_split,
        environments=envs,
        exclude_environments=excl,
        metrics=names,
    )
    info = {
        "store": str(store) if isinstance(store, str | Path) else [str(f) for f in ps.files],
        "train_environments": sorted(set(tr.environment.tolist())),
    }
    return train_images(
        cfg,
        tr,
        va,
        out_dir,
        label_thresholds=label_thresholds,
        data_info=info,
        matchers=store_matchers(ps, tr.index) or None,
    )


def store_matchers(store: Any, index: ArrayLike) -> list[str]:
    """Names of the matchers (pair-file ``matcher`` attribute) of the pairs ``index`` of a store.

    Args:
        store: A `scanguard.dataset.PairStore`.
        index: Record indices of the pairs.

    Returns:
        The sorted distinct names; empty when no file records its matcher.
    """
    files = np.unique(np.asarray(store.records["file"])[np.asarray(index, dtype=np.int64)])
    names = {str(store.file_attrs[int(f)].get("matcher", "")) for f in files.tolist()}
    return sorted(n for n in names if n)
