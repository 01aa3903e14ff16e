"""A detector's ONNX export: made, cached, and found again without PyTorch.

`export_onnx` writes a network as ONNX; `onnx_session` gives a detector an onnxruntime session
of its network's export, which is cached by the weights (`scanguard.fsutil.cache`: the export
takes ~0.7 s a process).

Reading a detector checkpoint needs PyTorch, whose import alone takes ~1.4 s (more than the
rest of a short run's start), and the onnxruntime back end then needs only the exported
network, which is cached by its weights (`scanguard.fsutil.cache`). So the first load of a file
with the ``onnx`` back end also remembers, under the digest of the file's bytes, the
checkpoint's metadata and the key of its export (`remember_export`); a later load of the same
bytes (the same file, a copy, the shipped model) builds the detector from those two alone
(`known_export`), and reads the weights only if something asks for the PyTorch network.

The entry is keyed by the file's bytes, this scanguard's version and the installed PyTorch's,
so it is never stale: a changed file, or a new release that reads checkpoints differently,
makes another key. Only a file that loaded without error is remembered, and only when its
metadata survive JSON unchanged, so a load from the cache gives the detector a load from the
file gives.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanguard.errors import ModelError, ScanGuardError
from scanguard.fsutil import atomic_path
from scanguard.fsutil.cache import cached_bytes, read_cached, store_cached
from scanguard.safeload import check_input_file

if TYPE_CHECKING:  # PyTorch is imported where a network is exported, not here
    from scanguard.detect.model import FaultCNN

log = logging.getLogger(__name__)

#: Cache folder of the entries (`scanguard.fsutil.cache`); the exports are under ``onnx``.
KIND = "onnx-detector"
ONNX_KIND = "onnx"
_FORMAT = "scanguard-onnx-detector"
#: Bumped when what an entry holds, or what a load derives from it, changes.
_VERSION = 1
_ONNX_KEY = re.compile(r"^[0-9a-f]{64}\.onnx$")


@dataclass(frozen=True)
class KnownExport:
    """A detector file seen before: its digest, metadata and exported network.

    Attributes:
        digest: SHA-256 of the file's bytes.
        checkpoint: The checkpoint without its weights (as `load_checkpoint` gave it).
        onnx: The exported network (ONNX bytes).
        onnx_key: The export's cache key (a digest of the weights and the exporter).
    """

    digest: str
    checkpoint: dict[str, Any]
    onnx: bytes
    onnx_key: str


def file_digest(path: Path) -> str:
    """SHA-256 of the file's bytes.

    Raises:
        ScanGuardError: Not a regular file (`scanguard.safeload.check_input_file`).
        OSError: The file cannot be read.
    """
    check_input_file(path, what="model file")
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "none"


def _entry_key(digest: str) -> str:
    made_by = f"{digest}|{_VERSION}|scanguard {_version('scanguard')}|torch {_version('torch')}"
    return hashlib.sha256(made_by.encode()).hexdigest() + ".json"


def known_export(digest: str) -> KnownExport | None:
    """The remembered export of the file of ``digest`` (`file_digest`); None: unseen, damaged."""
    raw = read_cached(KIND, _entry_key(digest))
    if raw is None:
        return None
    try:
        entry = json.loads(raw)
        ok = (
            isinstance(entry, dict)
            and entry.get("format") == _FORMAT
            and entry.get("version") == _VERSION
            and isinstance(entry.get("onnx"), str)
            and _ONNX_KEY.match(entry["onnx"]) is not None
            and isinstance(entry.get("checkpoint"), dict)
        )
    except ValueError:
        ok = False
    if not ok:
        log.debug("damaged cache entry %s: loading the file", _entry_key(digest))
        return None
    onnx = read_cached(ONNX_KIND, entry["onnx"])
    if onnx is None:
        return None
    return KnownExport(digest, entry["checkpoint"], onnx, entry["onnx"])


def remember_export(path: Path, digest: str, checkpoint: Mapping[str, Any], onnx_key: str) -> None:
    """Remember that the file at ``path`` (of digest ``digest``) loads as ``checkpoint``.

    ``digest`` is the file's digest taken before it was loaded; a file that changed while it
    was loaded is not remembered, nor metadata that JSON would change (a tuple, a tensor).
    """
    meta = {k: v for k, v in checkpoint.items() if k != "state_dict"}
    try:
        text = json.dumps(
            {"format": _FORMAT, "version": _VERSION, "onnx": onnx_key, "checkpoint": meta},
            allow_nan=False,
        )
        if json.loads(text)["checkpoint"] != meta or file_digest(path) != digest:
            return
    except (TypeError, ValueError, OSError, ScanGuardError):
        return
    if _ONNX_KEY.match(onnx_key) is None:
        return
    store_cached(KIND, _entry_key(digest), text.encode())


def export_onnx(model: FaultCNN, path: str | Path) -> Path:
    """Export a network to ONNX with a dynamic batch axis (written atomically).

    Inputs: ``images`` float32 NCHW in [0, 1], plus ``metrics`` ``(B, K)`` (the output of
    `scanguard.detect.model.metric_inputs`) for a hybrid model; output: ``logits`` ``(B, 2)``.

    Args:
        model: The network.
        path: Destination ``.onnx`` file.

    Returns:
        The path written.
    """
    import torch

    from scanguard.detect.model import build_model

    cfg = model.config
    m = build_model(cfg)
    m.load_state_dict({k: v.contiguous() for k, v in model.state_dict().items()})
    m.eval()
    dummy: tuple[torch.Tensor, ...] = (
        torch.zeros(1, cfg.in_channels, cfg.input_size, cfg.input_size),
    )
    names = ["images"]
    axes = {"images": {0: "batch"}, "logits": {0: "batch"}}
    if cfg.metrics:
        dummy += (torch.zeros(1, len(cfg.metrics)),)
        names.append("metrics")
        axes["metrics"] = {0: "batch"}
    p = Path(path)
    with atomic_path(p) as tmp, warnings.catch_warnings():
        # the TorchScript exporter is deprecated but needs no onnxscript and is exact here
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            m,
            dummy,
            str(tmp),
            input_names=names,
            output_names=["logits"],
            dynamic_axes=axes,
            opset_version=17,
            dynamo=False,
        )
    return p


def _onnx_key(model: FaultCNN) -> str:
    """Digest of everything the export depends on: weights, architecture, exporter."""
    import torch

    h = hashlib.sha256()
    h.update(f"opset17|torch {torch.__version__}|".encode())
    h.update(json.dumps(model.config.model_dump(mode="json"), sort_keys=True).encode())
    for name, tensor in model.state_dict().items():
        h.update(f"|{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return f"{h.hexdigest()}.onnx"


def _export_bytes(model: FaultCNN) -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return export_onnx(model, Path(d) / "model.onnx").read_bytes()


def session_of(data: bytes, threads: int) -> Any:
    """An onnxruntime session of an exported network.

    Raises:
        ModelError: onnxruntime is not installed, or refuses the bytes.
    """
    try:
        import onnxruntime as ort
    except ImportError:
        raise ModelError("onnx backend requested but onnxruntime is not installed") from None
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    # busy-waiting worker threads would steal CPU from the ICP running in the same process
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(data, sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own, unexported error types
        raise ModelError(f"onnxruntime refused the exported network: {exc}") from None


def onnx_session(model: FaultCNN, threads: int) -> tuple[Any, str]:
    """A session of the model's export and the export's cache key."""
    key = _onnx_key(model)
    # the export takes ~0.7 s per process; the cached one is the same export, keyed by the
    # weights, so only a damaged cache file (read back, then refused) is made again
    try:
        return session_of(cached_bytes("onnx", key, lambda: _export_bytes(model)), threads), key
    except ModelError as exc:
        if "not installed" in str(exc):
            raise
        log.warning("cached ONNX export %s unusable (%s): exporting again", key, exc)
    data = cached_bytes("onnx", key, lambda: _export_bytes(model), refresh=True)
    return session_of(data, threads), key


__all__ = [
    "KIND",
    "ONNX_KIND",
    "KnownExport",
    "export_onnx",
    "file_digest",
    "known_export",
    "onnx_session",
    "remember_export",
    "session_of",
]
