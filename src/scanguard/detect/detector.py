"""Inference with a trained fault-detection CNN (PyTorch eager or onnxruntime).

`FaultDetector.load()` without an argument loads the model shipped inside the package
(``scanguard/models/default.pt``). The detector renders a pair with the render style the
model was trained with, so callers only pass scans and the match estimate.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ValidationError

from scanguard.detect.calibrate import Calibration
from scanguard.detect.checkpoint_fields import LEGACY_MATCHER, check_threshold, checkpoint_matchers
from scanguard.detect.model_config import ModelConfig, metric_inputs
from scanguard.detect.onnx_export import (
    KnownExport,
    export_onnx,
    file_digest,
    known_export,
    onnx_session,
    remember_export,
    session_of,
)
from scanguard.detect.render import RenderStyle, render_pair, render_pairs
from scanguard.errors import MatchingError, ModelError, ScanError, ScanGuardError
from scanguard.matching.registry import get_matcher
from scanguard.pairs.features import pair_features
from scanguard.pairs.odometry import OdometryNoise
from scanguard.pairs.profile import PROFILE_FEATURES
from scanguard.scan import LaserScan

if TYPE_CHECKING:  # PyTorch is imported where the network itself is needed, not here
    from scanguard.detect.model import FaultCNN

log = logging.getLogger(__name__)

DEFAULT_MODEL_NAME = "default.pt"

Backend = Literal["torch", "onnx"]


def default_model_path(matcher: str | None = None) -> Path:
    """Path of the model shipped with the package for ``matcher``.

    ``default.pt`` covers the default back end's matcher (``icp-paper``, `LEGACY_MATCHER`);
    another matcher's model ships as ``<matcher>.pt`` when one was trained for it. A matcher
    without its own shipped model gets ``default.pt``, which `FaultDetector.check_matcher` then
    refuses unless told otherwise.

    Raises:
        MatchingError: ``matcher`` is not a registered matcher name.
    """
    folder = Path(str(resources.files("scanguard") / "models"))
    if matcher is not None:
        get_matcher(matcher)  # an unknown name is an error, not the default model
    if matcher is not None and matcher != LEGACY_MATCHER:
        own = folder / f"{matcher}.pt"
        if own.is_file():
            return own
    return folder / DEFAULT_MODEL_NAME


class FaultDetector:
    """Predicts the probability that a scan match is a fault.

    Attributes:
        model: The network (PyTorch, eval mode, channels-last).
        style: The `scanguard.detect.render.RenderStyle` the model was trained with.
        threshold: Operating threshold: a pair is a fault when probability >= threshold
            (a calibrated checkpoint's: the calibration block's threshold).
        calibration: The `scanguard.detect.calibrate.Calibration` applied to the fault logit
            (``None``: the network's softmax probability, unchanged).
        checkpoint: Checkpoint metadata (config, label thresholds, training info; no weights).
        backend: ``"torch"`` or ``"onnx"``.
        source: Where the model was loaded from.
    """

    def __init__(
        self,
        model: FaultCNN | None,
        style: Any,
        threshold: float = 0.5,
        *,
        checkpoint: dict[str, Any] | None = None,
        backend: Backend = "torch",
        source: str | Path = "<memory>",
        threads: int = 1,
        calibration: Calibration | None = None,
        export: KnownExport | None = None,
    ) -> None:
        """Wrap a trained model (see `FaultDetector.load` for files).

        Args:
            model: Trained network; None with ``export``: the network is read from ``source``
                only if `model` is asked for.
            style: `RenderStyle` (or its fields as a dict).
            threshold: Operating threshold on the fault probability.
            checkpoint: Metadata to keep (weights are dropped).
            backend: ``"torch"`` (eager, channels-last, inference mode) or ``"onnx"``.
            source: Description of the origin, used in messages.
            threads: Threads for onnxruntime (torch uses the process setting).
            calibration: Calibration of the fault probability (``None``: none).
            export: The ONNX export of the file ``source`` (`scanguard.detect.onnx_export`),
                with ``model`` None and the ``onnx`` back end.

        Raises:
            ModelError: ``threshold`` is not a probability in [0, 1], an unknown backend, or
                no model without the ONNX export of one.
        """
        if backend not in ("torch", "onnx"):
            raise ModelError(f"{source}: unknown backend {backend!r} (torch or onnx)")
        if model is None and (export is None or backend != "onnx"):
            raise ModelError(f"{source}: no model (only the onnx back end can do without one)")
        if model is not None:  # PyTorch is loaded already: the model is a module
            from scanguard.detect.model import inference_ready

            model = inference_ready(model)
        self._model = model
        self.style = style if isinstance(style, RenderStyle) else RenderStyle(**dict(style))
        self.threshold = check_threshold(threshold, source)
        self.checkpoint = {k: v for k, v in (checkpoint or {}).items() if k != "state_dict"}
        self.source = str(source)
        self.calibration = calibration
        self.backend: Backend = backend
        self._digest = None if export is None else export.digest
        cfg = _model_config(model, self.checkpoint, self.source)
        self.model_config = cfg
        self.input_shape = (cfg.input_size, cfg.input_size, cfg.in_channels)
        #: ICP metrics a hybrid model reads next to the image (empty: image-only CNN).
        self.metric_names: list[str] = list(cfg.metrics)
        # read once: the guard asks for these on every scan
        self._odometry_noise = _odometry_noise(self.checkpoint, self.source)
        self._reads_profile = any(n in PROFILE_FEATURES for n in self.metric_names)
        self._session: Any = None
        self.onnx_key: str | None = None
        if export is not None and backend == "onnx":
            self._session, self.onnx_key = session_of(export.onnx, threads), export.onnx_key
        elif backend == "onnx" and model is not None:
            self._session, self.onnx_key = onnx_session(model, threads)

    @property
    def model(self) -> FaultCNN:
        """The network (PyTorch, eval mode, channels-last).

        A detector built from a cached ONNX export reads it from its file when first asked.

        Raises:
            ModelError: The file is gone, or no longer the one the detector was built from.
        """
        if self._model is None:
            from scanguard.detect.checkpoint import load_checkpoint, model_from_checkpoint
            from scanguard.detect.model import inference_ready

            p = Path(self.source)
            try:
                same = file_digest(p) == self._digest
            except (OSError, ScanGuardError) as exc:
                raise ModelError(f"{p}: cannot read the network's weights ({exc})") from None
            if not same:
                raise ModelError(f"{p}: the file changed since the detector was loaded from it")
            self._model = inference_ready(model_from_checkpoint(load_checkpoint(p), p))
        return self._model

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        *,
        backend: Backend = "torch",
        threshold: float | None = None,
        threads: int = 1,
        calibrated: bool = True,
        matcher: str | None = None,
    ) -> FaultDetector:
        """Load a checkpoint (``None``: the model shipped with scanguard).

        With the ``onnx`` back end, a file whose export is cached (it was loaded so before)
        is built from the cache without PyTorch (`scanguard.detect.onnx_export`): the same
        detector, ~1.4 s sooner.

        Args:
            path: ``model.pt`` written by training, or a folder containing one; ``None``: the
                shipped model for ``matcher`` (`default_model_path`).
            backend: ``"torch"`` or ``"onnx"`` (needs onnxruntime).
            threshold: Override the checkpoint's operating threshold (default: the
                calibration block's threshold when applied, else the checkpoint's).
            threads: onnxruntime intra-op threads.
            calibrated: Apply the checkpoint's ``calibration`` block, if it has one (False:
                the raw network probability and the training threshold).
            matcher: With ``path=None``: the matcher whose shipped model to load.

        Raises:
            ModelError: Missing, corrupt or mismatched file, non-finite weights, an
                operating threshold that is not a probability in [0, 1], or a malformed
                ``matchers`` field (the message names the file).
        """
        p = default_model_path(matcher) if path is None else Path(path)
        if p.is_dir():
            p = p / "model.pt"
        try:
            digest: str | None = file_digest(p)
        except (OSError, ScanGuardError):
            digest = None  # load_checkpoint says what is wrong with the file
        known = known_export(digest) if backend == "onnx" and digest is not None else None
        if known is not None:
            try:
                return cls._assembled(None, known.checkpoint, p, backend, threshold, threads,
                                      calibrated, known)  # fmt: skip
            except ModelError as exc:  # a damaged export, say: the file decides
                log.debug("cached export of %s not used (%s): loading the file", p, exc)
        from scanguard.detect.checkpoint import load_checkpoint, model_from_checkpoint

        ckpt = load_checkpoint(p)
        model = model_from_checkpoint(ckpt, p)
        det = cls._assembled(model, ckpt, p, backend, threshold, threads, calibrated, None)
        if digest is not None and det.onnx_key is not None:
            remember_export(p, digest, ckpt, det.onnx_key)
        return det

    @classmethod
    def _assembled(
        cls,
        model: FaultCNN | None,
        ckpt: dict[str, Any],
        p: Path,
        backend: Backend,
        threshold: float | None,
        threads: int,
        calibrated: bool,
        export: KnownExport | None,
    ) -> FaultDetector:
        """The detector of a checkpoint's metadata (and network), checked as `load` says."""
        style = ckpt["style"]
        block = ckpt.get("calibration") if calibrated else None
        cal = None if block is None else Calibration.from_dict(block, p)
        default_threshold = float(ckpt["threshold"]) if cal is None else cal.threshold
        try:
            det = cls(
                model,
                style,
                default_threshold if threshold is None else threshold,
                checkpoint=ckpt,
                backend=backend,
                source=p,
                threads=threads,
                calibration=cal,
                export=export,
            )
        except ValidationError as exc:
            raise ModelError(f"{p}: invalid render style in checkpoint ({exc})") from None
        channels, cfg = det.style.channels, det.model_config
        if channels != cfg.in_channels or det.style.size != cfg.input_size:
            raise ModelError(
                f"{p}: render style {det.style.kind} {det.style.size}px x {channels} channels "
                f"does not match the "
                f"model input {cfg.input_size}px x {cfg.in_channels} channels"
            )
        checkpoint_matchers(ckpt, p)
        log.debug("loaded fault detector %s (%s, threshold %.3f)", p, backend, det.threshold)
        return det

    @property
    def label_thresholds(self) -> dict[str, Any]:
        """The labelling rule of the data the model was trained on."""
        return dict(self.checkpoint.get("label_thresholds", {}))

    @property
    def reads_odometry(self) -> bool:
        """The model also reads the odometry disagreement (`scanguard.pairs.odometry`)."""
        return "has_odometry" in self.metric_names

    @property
    def reads_profile(self) -> bool:
        """The model also reads the per-beam residual profile (`scanguard.pairs.profile`)."""
        return self._reads_profile

    @property
    def odometry_noise(self) -> OdometryNoise:
        """The noise model that scales the odometry disagreement.

        The checkpoint's, or the one fitted to the robot's recording (`use_odometry_noise`).
        """
        return self._odometry_noise

    def use_odometry_noise(self, noise: OdometryNoise) -> None:
        """Scale the odometry disagreement with ``noise`` from now on (this robot's model)."""
        self._odometry_noise = noise

    @property
    def matchers(self) -> tuple[str, ...]:
        """Names of the matchers whose matches the model was trained on.

        A checkpoint without the field (the shipped model, older checkpoints) was trained on
        `LEGACY_MATCHER` (``icp-paper``) matches.
        """
        return checkpoint_matchers(self.checkpoint, self.source)

    def check_matcher(self, name: str, *, allow_other: bool = False) -> bool:
        """Check that the model was trained on matches of the matcher ``name``.

        Args:
            name: Registered matcher name (e.g. ``"plicp"``).
            allow_other: Use the model on another matcher's matches anyway (logged as a
                warning; its verdicts are then uncalibrated).

        Returns:
            True when the model was trained for ``name``; False when it was not but
            ``allow_other`` is set.

        Raises:
            ModelError: The model was not trained for ``name`` and ``allow_other`` is off.
        """
        trained = self.matchers
        if name in trained:
            return True
        what = " or ".join(trained)
        if not allow_other:
            raise ModelError(
                f"model {self.source} was trained on {what} matches, not {name}: pass "
                "--allow-other-matcher to use it anyway (its verdicts are then uncalibrated)"
            )
        log.warning(
            "model %s was trained on %s matches, not %s: its verdicts are uncalibrated",
            self.source,
            what,
            name,
        )
        return False

    def predict_images(
        self,
        images: NDArray[np.uint8],
        batch_size: int = 256,
        *,
        features: Mapping[str, ArrayLike] | NDArray[np.floating[Any]] | None = None,
    ) -> NDArray[np.float64]:
        """Fault probabilities of rendered pairs.

        Args:
            images: uint8 ``(B, H, W, C)`` (or one ``(H, W, C)`` image) in the model's style.
            batch_size: Images per forward pass.
            features: For a hybrid model (`metric_names` not empty): the pairs' ICP metrics,
                as columns by name (a pair store's records, or `match_features`) or an
                already transformed ``(B, K)`` array (`scanguard.detect.model.metric_inputs`).
                Ignored by an image-only model.

        Returns:
            ``(B,)`` probabilities of the fault class (calibrated when the detector has a
            `calibration`).

        Raises:
            ModelError: Wrong image shape or dtype, or missing metrics for a hybrid model.
        """
        if self.calibration is None:
            return self._forward(images, batch_size, features, "raw")
        return self._forward(images, batch_size, features, "calibrated")

    def predict_logits(
        self,
        images: NDArray[np.uint8],
        batch_size: int = 256,
        *,
        features: Mapping[str, ArrayLike] | NDArray[np.floating[Any]] | None = None,
    ) -> NDArray[np.float64]:
        """Fault logit margins ``z = logit_fault - logit_normal`` (never calibrated).

        The uncalibrated probability is ``sigmoid(z)``; a calibration maps ``z`` to its
        probability (`scanguard.detect.calibrate.Calibration.apply`). Arguments and errors as
        `predict_images`.
        """
        return self._forward(images, batch_size, features, "logit")

    def _forward(
        self,
        images: NDArray[np.uint8],
        batch_size: int,
        features: Mapping[str, ArrayLike] | NDArray[np.floating[Any]] | None,
        mode: Literal["raw", "calibrated", "logit"],
    ) -> NDArray[np.float64]:
        arr = np.asarray(images)
        if arr.ndim == 3:
            arr = arr[None]
        if arr.ndim != 4 or arr.shape[1:] != self.input_shape:
            raise ModelError(
                f"{self.source}: expected images (B, {', '.join(map(str, self.input_shape))}), "
                f"got {arr.shape}"
            )
        if arr.dtype != np.uint8:
            raise ModelError(f"{self.source}: expected uint8 images, got {arr.dtype}")
        met: NDArray[np.float32] | None = None
        if self.metric_names:
            if features is None:
                raise ModelError(
                    f"{self.source}: this model also reads the ICP metrics {self.metric_names}; "
                    "pass features= (or match= to fault_probability)"
                )
            try:
                met = np.ascontiguousarray(metric_inputs(features, self.metric_names))
            except Exception as exc:  # ConfigError: a metric is missing
                raise ModelError(f"{self.source}: {exc}") from None
            if len(met) != len(arr):
                raise ModelError(f"{self.source}: {len(arr)} images but {len(met)} metric rows")
        out = np.empty(len(arr), dtype=np.float64)
        for s in range(0, len(arr), batch_size):
            chunk = arr[s : s + batch_size]
            mchunk = None if met is None else met[s : s + batch_size]
            if self._session is not None:
                x = chunk.transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255.0)
                feed = {"images": np.ascontiguousarray(x)}
                if mchunk is not None:
                    feed["metrics"] = mchunk
                logits = self._session.run(None, feed)[0]
                if mode == "raw":
                    z = logits - logits.max(axis=1, keepdims=True)
                    e = np.exp(z.astype(np.float64))
                    out[s : s + len(chunk)] = e[:, 1] / e.sum(axis=1)
                    continue
                l64 = np.asarray(logits, dtype=np.float64)
            else:
                from scanguard.detect.model import forward_numpy

                l64, proba = forward_numpy(self.model, chunk, mchunk, mode == "raw")
                if proba is not None:
                    out[s : s + len(chunk)] = proba
                    continue
            margin = l64[:, 1] - l64[:, 0]
            if mode == "calibrated" and self.calibration is not None:
                out[s : s + len(chunk)] = self.calibration.apply(margin)
            else:
                out[s : s + len(chunk)] = margin
        return out

    def render(self, previous: LaserScan, current: LaserScan, pose: ArrayLike) -> NDArray[np.uint8]:
        """The image of one pair, as the model sees it."""
        return render_pair(previous, current, np.asarray(pose, dtype=np.float64), self.style)

    def match_features(
        self,
        previous: LaserScan | NDArray[np.floating[Any]],
        current: LaserScan | NDArray[np.floating[Any]],
        match: Any,
        odometry: ArrayLike | None = None,
    ) -> dict[str, NDArray[np.float64]]:
        """Metric columns (length 1) of one matched pair, as a hybrid model reads them.

        ``previous``/``current`` may be scans or their ``(N, 2)`` points (a caller that already
        has the points saves converting them again).

        ``match.metrics()`` (`scanguard.matching.MatchResult`) plus, when the model reads
        ``gmapping_score_norm``, `scanguard.matching.quality.gmapping_score` of the pair — the same
        definitions the dataset stores — plus, for a model that reads it, the odometry
        disagreement of the match (`scanguard.pairs.odometry.odometry_disagreement`) with
        ``odometry``, the odometry increment ``(3,)`` in the sensor frame (the estimate's
        convention; ``None``: this pair has no odometry, the mask says so).
        """
        if not callable(getattr(match, "metrics", None)):
            raise ModelError(f"{self.source}: match has no metrics() (a MatchResult is needed)")
        return pair_features(
            previous,
            current,
            match,
            gmapping=any(n.startswith("gmapping") for n in self.metric_names),
            profile=self.reads_profile,
            odometry=odometry,
            noise=self.odometry_noise,
            with_odometry=self.reads_odometry,
        )

    def fault_probability(
        self,
        previous: LaserScan,
        current: LaserScan,
        pose: ArrayLike,
        match: Any = None,
        odometry: ArrayLike | None = None,
    ) -> float:
        """Probability that ``pose`` (the match of ``current`` onto ``previous``) is a fault.

        Args:
            previous: Previous scan (ICP target).
            current: Current scan (ICP source).
            pose: Match estimate.
            match: The `scanguard.matching.MatchResult`; required by a hybrid model (its
                quality metrics), ignored by an image-only one.
            odometry: Odometry increment ``(3,)`` of the pair in the sensor frame, for a model
                that reads the odometry disagreement (``None``: no odometry).

        Raises:
            ScanError: ``previous`` or ``current`` is not a `LaserScan`.
            MatchingError: ``pose`` or ``odometry`` is not 3 finite numbers.
            ModelError: A hybrid model without ``match``.
        """
        pose = _pair_pose(pose, "pose")
        if odometry is not None:
            odometry = _pair_pose(odometry, "odometry")
        for name, scan in (("previous", previous), ("current", current)):
            if not isinstance(scan, LaserScan):
                raise ScanError(f"{name} must be a LaserScan, got {type(scan).__name__}")
        feats = None
        if self.metric_names:
            if match is None:
                raise ModelError(f"{self.source}: this model also reads ICP metrics; pass match=")
            feats = self.match_features(previous, current, match, odometry)
        image = self.render(previous, current, pose)[None]
        return float(self.predict_images(image, features=feats)[0])

    def is_fault(
        self,
        previous: LaserScan,
        current: LaserScan,
        pose: ArrayLike,
        match: Any = None,
        odometry: ArrayLike | None = None,
    ) -> bool:
        """``fault_probability >= threshold``."""
        return self.fault_probability(previous, current, pose, match, odometry) >= self.threshold

    def predict_pairs(
        self,
        previous: Sequence[LaserScan],
        current: Sequence[LaserScan],
        poses: ArrayLike,
        batch_size: int = 256,
        *,
        features: Mapping[str, ArrayLike] | NDArray[np.floating[Any]] | None = None,
    ) -> NDArray[np.float64]:
        """Fault probabilities ``(B,)`` of many pairs (rendered, then batched).

        ``features`` are the pairs' ICP metrics for a hybrid model (see `predict_images`).
        """
        p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if not (len(previous) == len(current) == len(p)):
            raise ModelError(
                f"{self.source}: {len(previous)} previous scans, {len(current)} current scans "
                f"and {len(p)} poses"
            )
        if len(p) == 0:
            return np.zeros(0, dtype=np.float64)
        images = render_pairs(list(previous), list(current), p, self.style)
        return self.predict_images(images, batch_size, features=features)

    def export_onnx(self, path: str | Path) -> Path:
        """Write the network as ONNX (see `export_onnx`)."""
        return export_onnx(self.model, path)


def _model_config(
    model: FaultCNN | None, checkpoint: Mapping[str, Any], source: str
) -> ModelConfig:
    """The network's architecture: the model's own, else the checkpoint's ``model_config``."""
    if model is not None:
        return model.config
    try:
        return ModelConfig.model_validate(checkpoint["model_config"])
    except (KeyError, ValidationError) as exc:
        raise ModelError(f"{source}: invalid model config in checkpoint ({exc})") from None


def _pair_pose(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """``value`` as 3 finite floats (a match estimate or an odometry increment)."""
    try:
        p = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise MatchingError(
            f"{name} must be 3 numbers (x, y, theta), got {type(value).__name__}"
        ) from None
    if p.shape != (3,):
        raise MatchingError(f"{name} must be 3 numbers (x, y, theta), got shape {p.shape}")
    if not np.isfinite(p).all():
        raise MatchingError(f"{name} must be finite, got {p.tolist()}")
    return p


def _odometry_noise(checkpoint: Mapping[str, Any], source: str) -> OdometryNoise:
    """The checkpoint's ``odometry_noise`` block (the default model when it has none)."""
    block = checkpoint.get("odometry_noise")
    if not block:
        return OdometryNoise()
    try:
        return OdometryNoise.model_validate(block)
    except ValidationError as exc:
        raise ModelError(f"{source}: invalid odometry_noise block ({exc})") from None
