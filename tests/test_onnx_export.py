"""A detector file loaded again with the onnx back end comes from the cache, without PyTorch."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scanguard.detect.detector import FaultDetector
from scanguard.errors import ModelError
from tests.test_detector import trained  # noqa: F401 (the fixture)

pytest.importorskip("onnxruntime")


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A cache folder of the test's own (``XDG_CACHE_HOME``)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _images() -> np.ndarray:
    return (np.random.default_rng(1).random((6, 32, 32, 2)) < 0.05).astype(np.uint8) * 255


def _no_file_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    import scanguard.detect.checkpoint as checkpoint_mod

    def refuse(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("the checkpoint was read")

    monkeypatch.setattr(checkpoint_mod, "load_checkpoint", refuse)


def test_second_load_is_the_same_detector_without_the_checkpoint(
    trained: Path,  # noqa: F811
    cache: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    first = FaultDetector.load(trained, backend="onnx")
    expected = first.predict_images(_images())
    _no_file_reads(monkeypatch)
    again = FaultDetector.load(trained, backend="onnx")
    np.testing.assert_array_equal(again.predict_images(_images()), expected)
    for name in ("threshold", "metric_names", "input_shape", "checkpoint", "matchers"):
        assert getattr(again, name) == getattr(first, name), name
    assert again.style == first.style and again.model_config == first.model_config
    assert again.onnx_key == first.onnx_key
    # an override and the raw probability are applied as for a load from the file
    raw = FaultDetector.load(trained, backend="onnx", threshold=0.3, calibrated=False)
    assert raw.threshold == 0.3 and raw.calibration is None


def test_the_network_is_read_from_the_file_when_asked(
    trained: Path,  # noqa: F811
    cache: Path,
    tmp_path: Path,
) -> None:
    copy = tmp_path / "model.pt"
    shutil.copyfile(trained, copy)
    FaultDetector.load(copy, backend="onnx")
    lazy = FaultDetector.load(copy, backend="onnx")
    assert lazy._model is None  # built from the cache
    eager = FaultDetector.load(copy)  # torch back end: from the file
    for (name, a), (_, b) in zip(
        lazy.model.state_dict().items(), eager.model.state_dict().items(), strict=True
    ):
        assert a.equal(b), name
    stale = FaultDetector.load(copy, backend="onnx")
    copy.write_bytes(copy.read_bytes() + b"\0")  # the file is no longer the one loaded
    with pytest.raises(ModelError, match="changed since"):
        _ = stale.model


def test_a_changed_or_damaged_entry_falls_back_to_the_file(
    trained: Path,  # noqa: F811
    cache: Path,
    tmp_path: Path,
) -> None:
    from scanguard.detect import onnx_export

    expected = FaultDetector.load(trained, backend="onnx").predict_images(_images())
    entries = list((cache / "scanguard" / onnx_export.KIND).iterdir())
    assert len(entries) == 1
    entries[0].write_text('{"format": "something else"}')
    assert onnx_export.known_export(onnx_export.file_digest(trained)) is None
    again = FaultDetector.load(trained, backend="onnx")
    np.testing.assert_array_equal(again.predict_images(_images()), expected)
    digest = onnx_export.file_digest(trained)
    assert onnx_export.known_export(digest) is not None  # remembered again
    # a corrupt file is still refused in one line, whatever the cache holds
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ModelError, match=r"bad\.pt"):
        FaultDetector.load(bad, backend="onnx")


def test_a_run_start_does_not_import_torch_once_the_export_is_cached(
    trained: Path,  # noqa: F811
    tmp_path: Path,
) -> None:
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    code = (
        "import sys; from scanguard.detect.detector import FaultDetector; "
        f"d = FaultDetector.load({str(trained)!r}, backend='onnx'); "
        "print('torch' in sys.modules, d.threshold)"
    )
    runs = [
        subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        for _ in range(2)
    ]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr + runs[1].stderr
    first, second = (r.stdout.split() for r in runs)
    assert first[0] == "True" and second[0] == "False"  # the file, then the cache
    assert first[1] == second[1]  # the same threshold
