"""Hostile suite, third audit (issue 32, item 2): edited pair stores and foreign model files.

A pair store edited by hand (a ``prev`` index past the scans, a ``label`` dataset missing or
shorter than the others, a corrupt chunk) is refused when it is opened, in one line naming
the file and the field, by every command that reads one; a YAML file given as a model is one
line too. Before the fix these ended in an ``IndexError``, ``KeyError`` or ``ValueError``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from scanguard.dataset import PairStore
from scanguard.errors import FormatError, ModelError
from tests.test_dataset import write_two
from tests.test_hostile_cli import LOG, invoke, one_line_error


def _prev_out_of_range(f: h5py.File) -> None:
    prev = f["pairs/prev"][()]
    prev[2] = 999
    f["pairs/prev"][...] = prev


def _label_missing(f: h5py.File) -> None:
    del f["pairs/label"]


def _label_shorter(f: h5py.File) -> None:
    label = f["pairs/label"][()]
    del f["pairs/label"]
    f["pairs"].create_dataset("label", data=label[:-2])


def _label_value(f: h5py.File) -> None:
    label = f["pairs/label"][()]
    label[0] = 7
    f["pairs/label"][...] = label


def _metric_shorter(f: h5py.File) -> None:
    name = next(iter(f["pairs/metrics"]))
    data = f["pairs/metrics"][name][()]
    del f["pairs/metrics"][name]
    f["pairs/metrics"].create_dataset(name, data=data[:1])


EDITS: dict[str, tuple[Callable[[h5py.File], None], str]] = {
    "prev out of range": (_prev_out_of_range, "/pairs/prev[2] = 999 is not a scan index"),
    "label missing": (_label_missing, "lacks the /pairs/label dataset"),
    "label shorter": (_label_shorter, "differ in length: label 3 rows where the others have 5"),
    "label value": (_label_value, "/pairs/label holds values other than -1, 0 and 1"),
    "metric shorter": (_metric_shorter, "has shape (1,), expected (5,)"),
}


def _commands(store: Path, out: Path) -> dict[str, list[str]]:
    return {
        "dataset stats": ["dataset", "stats", str(store), "-o", str(out)],
        "dataset export-png": ["dataset", "export-png", str(store), "-o", str(out)],
        "evaluate": ["evaluate", "-d", str(store), "--baselines", "none", "-o", str(out)],
        "calibrate": ["calibrate", "-d", str(store), "-o", str(out)],
    }


@pytest.mark.parametrize("edit", list(EDITS))
def test_edited_store_is_refused_at_open_naming_file_and_field(edit: str, tmp_path: Path) -> None:
    paths = write_two(tmp_path)
    change, problem = EDITS[edit]
    with h5py.File(paths[1], "r+") as f:
        change(f)
    with pytest.raises(FormatError) as info:
        PairStore.open(paths)
    assert str(info.value).startswith(str(paths[1])) and problem in str(info.value)


@pytest.mark.parametrize(
    "command", ["dataset stats", "dataset export-png", "evaluate", "calibrate"]
)
def test_every_store_command_refuses_an_edited_store_in_one_line(
    command: str, tmp_path: Path
) -> None:
    paths = write_two(tmp_path)
    with h5py.File(paths[0], "r+") as f:
        _prev_out_of_range(f)
    out = tmp_path / "out"
    one_line_error(invoke(*_commands(paths[0], out)[command]), "room_00.h5", "/pairs/")
    assert not out.exists()


def test_corrupt_hdf5_chunk_names_the_file(tmp_path: Path) -> None:
    paths = write_two(tmp_path)
    with h5py.File(paths[0], "r") as f:
        info = f["scans/ranges"].id.get_chunk_info(0)
    with open(paths[0], "r+b") as fh:  # garble the compressed scans: inflate() fails
        fh.seek(info.byte_offset)
        fh.write(bytes(np.random.default_rng(0).integers(0, 256, info.size, dtype=np.uint8)))
    out = tmp_path / "out"
    line = one_line_error(invoke("dataset", "export-png", str(paths[0]), "-o", out), "room_00.h5")
    assert "/scans/ranges" in line and "corrupt" in line
    assert not out.exists()


# --- 8: a YAML file as a model --------------------------------------------------------------------


def test_yaml_as_model_is_a_one_line_model_error(tmp_path: Path) -> None:
    from scanguard.detect.checkpoint import load_checkpoint

    model = tmp_path / "model.yaml"
    model.write_text("matcher: icp-paper\nthreshold: 0.5\nlayers: [1, 2, 3]\n")
    with pytest.raises(ModelError, match=r"model.yaml: not a readable model checkpoint"):
        load_checkpoint(model)
    paths = write_two(tmp_path / "src")
    out = tmp_path / "o"
    for args in (
        ["export", "onnx", "-m", model, "-o", tmp_path / "m.onnx"],
        ["calibrate", "-m", model, "-d", paths[0], "-o", out],
        ["run", "-m", model, LOG, "-o", out, "--backend", "frontend", "--baseline", "none"],
    ):
        one_line_error(invoke(*args), "model.yaml", "not a readable model checkpoint")
    assert not out.exists()


# --- 16: calibrate never writes a model from data that determine no calibration ----------------


def test_calibrate_on_a_single_pair_refuses_in_one_line(tmp_path: Path) -> None:
    out = tmp_path / "cal"
    args = ["calibrate", "-r", LOG, "--max-scans", "2", "-o", out]
    line = one_line_error(invoke(*args), LOG.name, "at least 3 of each class")
    assert "normal and" in line and not out.exists()


@pytest.mark.parametrize(
    ("labels", "logits", "problem"),
    [
        ([1], [2.0], "0 normal and 1 fault"),
        ([0, 0, 0, 0], [-1.0, 0.5, 2.0, -3.0], "4 normal and 0 fault"),
        ([0, 0, 0, 1, 1, 1], [-5.0, -4.0, -3.0, 3.0, 4.0, 5.0], "perfectly separated"),
        ([0, 0, 0, 1, 1, 1], [5.0, 4.0, 3.0, -3.0, -4.0, -5.0], "not separated at all"),
    ],
)
def test_degenerate_calibration_data_are_refused(labels, logits, problem, tmp_path: Path) -> None:
    from scanguard.detect.detector import FaultDetector
    from scanguard.detect.recalibrate import calibrate_detector
    from scanguard.errors import ConfigError

    det = FaultDetector.load(None)
    with pytest.raises(ConfigError, match=problem):
        calibrate_detector(det, (np.array(labels), np.array(logits)), method="temperature")
