"""Hostile inputs, second audit (issue 24): bounded YAML/JSON, special files, names as paths,
destinations scanguard did not write, full disks, hostile model files, Markdown cells.

Every case is fast and seeded, and checks the known answer: exit 1 with one line
``error: <file>: ...``, and every file that was there untouched.
"""

from __future__ import annotations

import base64
import errno
import json
import os
import pickle
import time
from pathlib import Path
from typing import Any

import h5py
import pytest
import torch

from scanguard.apps.batch import md_cell, write_table
from scanguard.config import YamlModel
from scanguard.dataset import PairStore, merge_stores
from scanguard.detect.baselines.registry import load_detector, save_detector
from scanguard.detect.baselines.threshold import ThresholdDetector
from scanguard.detect.checkpoint import load_checkpoint
from scanguard.errors import (
    ConfigError,
    FormatError,
    InputError,
    ModelError,
    OutputError,
)
from scanguard.fsutil import ResultDir, atomic_path, atomic_write_text, check_file_name
from scanguard.io import read_sequence
from scanguard.io.tum import read_tum
from scanguard.safeload import load_json, loads_json, loads_yaml
from scanguard.sim import parse_overrides
from scanguard.sim.output import check_bag_output
from scanguard.slam.graph.judges import load_closure_judge
from tests.test_dataset import write_two
from tests.test_hostile_cli import invoke, one_line_error

MODELS = Path(__file__).resolve().parents[1] / "src" / "scanguard" / "models"


def alias_bomb(levels: int = 9) -> str:
    """The classic "billion laughs": ~1 KB that expands to 9**levels values."""
    text = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    prev = "a"
    for k in range(levels - 1):
        name = f"b{k}"
        text += f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 9) + "]\n"
        prev = name
    return text


def tree(tmp: Path) -> dict[str, bytes]:
    return {str(p.relative_to(tmp)): p.read_bytes() for p in tmp.rglob("*") if p.is_file()}


# --- the bounded loader (defects 4 and 12) ----------------------------------------------------


def test_alias_bomb_fails_fast_with_the_file() -> None:
    t0 = time.perf_counter()
    with pytest.raises(FormatError, match=r"^bomb.yaml: not valid YAML \(expands to more than"):
        loads_yaml(alias_bomb(), "bomb.yaml")
    assert time.perf_counter() - t0 < 0.5
    # a document with honest aliases still loads, with the alias followed
    assert loads_yaml("a: &x [1, 2]\nb: *x\n", "ok.yaml") == {"a": [1, 2], "b": [1, 2]}


@pytest.mark.parametrize(
    "text",
    [
        "[" * 50_000,
        "{a: " * 5_000 + "1" + "}" * 5_000,
        "".join("  " * i + "k:\n" for i in range(200)),
    ],
)
def test_deep_yaml_is_refused(text: str) -> None:
    with pytest.raises(FormatError, match=r"^deep.yaml: not valid YAML") as info:
        loads_yaml(text, "deep.yaml")
    assert "\n" not in str(info.value)


def test_deep_json_is_refused_without_recursion_error(tmp_path: Path) -> None:
    p = tmp_path / "deep.json"
    p.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ModelError, match=r"deep\.json: not valid JSON \(nested deeper than 64"):
        load_json(p, error=ModelError)
    assert loads_json('{"a": [1, {"b": 2}]}', "x") == {"a": [1, {"b": 2}]}


class _Cfg(YamlModel):
    a: int = 1


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (alias_bomb().encode(), "alias bomb"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe" * 10, "not a text file"),
        (("[" * 50_000).encode(), "not valid YAML"),
        (b"- 1\n- 2\n", "not a mapping"),
    ],
)
def test_config_files_fail_in_one_line(tmp_path: Path, content: bytes, needle: str) -> None:
    p = tmp_path / "c.yaml"
    p.write_bytes(content)
    with pytest.raises(ConfigError, match=f"^{p}: ") as info:
        _Cfg.from_yaml(p)
    assert needle in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "args",
    [
        ["dataset", "build", "-c", "{cfg}", "-o", "{out}"],
        ["simulate", "--scenario", "{cfg}", "-d", "1", "-o", "{out}.mcap"],
        ["train", "-c", "{cfg}", "-d", "missing-store", "-o", "{out}"],
        ["run", "missing.log", "--config", "{cfg}", "-o", "{out}"],
    ],
)
@pytest.mark.parametrize("kind", ["bomb", "binary", "deep"])
def test_cli_configs_bounded(tmp_path: Path, args: list[str], kind: str) -> None:
    cfg = tmp_path / "c.yaml"
    content = {
        "bomb": alias_bomb().encode(),
        "binary": bytes(range(256)) * 4,
        "deep": ("a:\n" + "".join("  " * i + "b:\n" for i in range(1, 400))).encode(),
    }[kind]
    cfg.write_bytes(content)
    out = tmp_path / "out"
    t0 = time.perf_counter()
    res = invoke(*[a.format(cfg=cfg, out=out) for a in args])
    assert time.perf_counter() - t0 < 5
    one_line_error(res, "c.yaml")
    assert not out.exists() and not Path(f"{out}.mcap").exists()


def test_set_bomb_is_one_line() -> None:
    with pytest.raises(ConfigError, match="invalid YAML in --set") as info:
        parse_overrides([f"people={'[' * 50_000}"])
    assert len(str(info.value)) < 300
    bomb = "{a: &a [1,1,1,1,1,1,1,1,1], " + ", ".join(
        f"b{k}: &b{k} [" + ", ".join([f"*{'a' if k == 0 else f'b{k - 1}'}"] * 9) + "]"
        for k in range(8)
    )
    with pytest.raises(ConfigError, match="alias bomb"):
        parse_overrides([f"sensor={bomb}}}"])


def test_ros2_metadata_bomb_is_refused(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(alias_bomb())
    (bag / "bag.mcap").write_bytes(b"\x89MCAP0\r\n")
    t0 = time.perf_counter()
    with pytest.raises(FormatError, match=r"metadata.yaml: not valid YAML"):
        read_sequence(bag)
    one_line_error(invoke("info", bag), "metadata.yaml", "alias bomb")
    (bag / "metadata.yaml").write_text("[" * 50_000)
    one_line_error(invoke("info", bag), "metadata.yaml", "not valid YAML")
    assert time.perf_counter() - t0 < 5


# --- one input-path check (defect 6) ----------------------------------------------------------


@pytest.mark.parametrize("name", ["x.bag", "x.mcap", "x.log", "x.clf.gz"])
def test_fifo_recording_never_blocks(tmp_path: Path, name: str) -> None:
    fifo = tmp_path / name
    os.mkfifo(fifo)
    t0 = time.perf_counter()
    one_line_error(invoke("info", fifo), name, "a FIFO (named pipe), not a regular file")
    assert time.perf_counter() - t0 < 5


def test_special_inputs_are_named_not_missing(tmp_path: Path) -> None:
    fifo = tmp_path / "p"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match=r"a FIFO .* not read as a TUM trajectory file"):
        read_tum(fifo)
    with pytest.raises(ConfigError, match=r"a FIFO .* not read as a config file"):
        _Cfg.from_yaml(fifo)
    with pytest.raises(ModelError, match=r"a FIFO .* not read as a model file"):
        load_checkpoint(fifo)
    with pytest.raises(ModelError, match="a folder, not a regular file"):
        load_detector(tmp_path)
    with pytest.raises(ConfigError, match="a device, not a regular file"):
        _Cfg.from_yaml("/dev/null")
    with pytest.raises(ConfigError, match="config file not found"):
        _Cfg.from_yaml(tmp_path / "missing.yaml")
    one_line_error(invoke("info", "/dev/zero"), "/dev/zero", "a device")


# --- names never become paths (defect 1) ------------------------------------------------------


def test_environment_name_cannot_leave_the_output(tmp_path: Path) -> None:
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    victim = tmp_path / "victim_00.h5"
    victim.write_bytes(b"precious")
    cfg = work / "t.yaml"
    cfg.write_text(
        'environments: [{name: "../../victim", scenario: lobby, sequences: 1, duration: 4}]\n'
    )
    before = tree(tmp_path)
    line = one_line_error(invoke("dataset", "build", "-c", cfg, "-o", work / "out"), "t.yaml")
    assert "environment name '../../victim' cannot be a file name" in line
    assert tree(tmp_path) == before
    for bad in ("..", ".hidden", "a/b", "a\\b", "", "x\ny", "c:x"):
        with pytest.raises(ValueError):
            check_file_name(bad)
    assert check_file_name("lobby_00") == "lobby_00"


def test_merge_of_a_shard_named_dot_dot(tmp_path: Path) -> None:
    paths = write_two(tmp_path / "src")
    with h5py.File(paths[0], "r+") as f:
        f.attrs["sequence"] = "../../x"
    before = tree(tmp_path)
    with pytest.raises(InputError, match=r"sequence name '../../x' cannot be a file name"):
        merge_stores(paths, tmp_path / "m" / "out")
    line = one_line_error(invoke("dataset", "merge", *paths, "-o", tmp_path / "m" / "out"))
    assert "room_00.h5" in line
    assert tree(tmp_path) == before and not (tmp_path / "m").exists()


# --- destinations scanguard did not write (defects 2 and 3) -----------------------------------


def test_merge_refuses_an_existing_dataset(tmp_path: Path) -> None:
    paths = write_two(tmp_path / "src")
    big = merge_stores(paths, tmp_path / "big")
    (big / ".scanguard-complete.json").unlink()  # as a dataset build leaves it: no marker
    small = merge_stores(paths[:1], tmp_path / "small")
    before = tree(big)
    line = one_line_error(invoke("dataset", "merge", small, "-o", big), "big", "--overwrite")
    assert "was not written by scanguard" in line
    assert tree(big) == before and len(PairStore.open(big)) == 2 * len(PairStore.open(small))
    # with --overwrite it is written; a merge result is replaced as a whole by the next merge
    res = invoke("dataset", "merge", small, "-o", big, "--overwrite")
    assert res.exit_code == 0, res.output
    assert len(PairStore.open(big)) == len(PairStore.open(small))
    res = invoke("dataset", "merge", *paths, "-o", small)
    assert res.exit_code == 0, res.output
    assert len(PairStore.open(small)) == len(PairStore.open(big)) * 2


def test_user_folder_with_a_manifest_is_refused(tmp_path: Path) -> None:
    paths = write_two(tmp_path / "src")
    mine = tmp_path / "mine"
    (mine / "sequences").mkdir(parents=True)
    (mine / "manifest.json").write_text("my notes")
    (mine / "sequences" / "room_00.h5").write_bytes(b"mine")
    before = tree(mine)
    one_line_error(invoke("dataset", "merge", *paths, "-o", mine), "mine", "--overwrite")
    assert tree(mine) == before


def test_simulate_keeps_what_it_did_not_write(tmp_path: Path) -> None:
    bag = tmp_path / "mybag"
    bag.mkdir()
    (bag / "metadata.yaml").touch()
    (bag / "NOTES.txt").write_text("notes")
    rec = tmp_path / "existing.mcap"
    rec.write_bytes(b"\x89MCAP0\r\n a real recording")
    before = tree(tmp_path)
    for dest in (bag, rec):
        line = one_line_error(invoke("simulate", "-d", "0.3", "-o", dest), dest.name)
        assert "not replacing it" in line
    one_line_error(invoke("simulate", "-d", "0.3", "-o", bag, "--overwrite"), "NOTES.txt")
    assert tree(tmp_path) == before
    with pytest.raises(OutputError, match="pass --overwrite"):
        check_bag_output(rec)
    assert check_bag_output(rec, overwrite=True) == rec.resolve()


def test_simulate_replaces_its_own_mcap(tmp_path: Path) -> None:
    dest = tmp_path / "run.mcap"
    for seed in ("1", "2"):
        res = invoke("simulate", "-d", "0.3", "--seed", seed, "--set", "people.count=0", "-o", dest)
        assert res.exit_code == 0, res.output
    assert read_sequence(dest).metadata["seed"] == 2


# --- a full disk (defects 5 and 19) -----------------------------------------------------------


def _enospc(*args: Any, **kwargs: Any) -> Any:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_enospc_in_a_file_write_names_the_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dest = tmp_path / "summary.md"
    dest.write_text("previous")
    monkeypatch.setattr(Path, "write_text", _enospc)
    with pytest.raises(OutputError, match=f"^{dest}: no space left on device"):
        atomic_write_text(dest, "new")
    monkeypatch.undo()
    assert dest.read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == [dest.name]


def test_enospc_from_hdf5_names_the_path(tmp_path: Path) -> None:
    dest = tmp_path / "s.h5"
    dest.write_bytes(b"previous")
    h5_text = "Can't write data (file write failed: errno = 28, error message = 'No space left')"
    with pytest.raises(OutputError, match=r"s\.h5: no space left") as info, atomic_path(dest):
        raise OSError(h5_text)
    assert info.value.__cause__ is None and "\n" not in str(info.value)
    assert dest.read_bytes() == b"previous" and len(list(tmp_path.iterdir())) == 1


def test_enospc_in_a_result_folder_keeps_the_previous_result(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with ResultDir(out, record={"name": "t"}) as tmp:
        (tmp / "a.txt").write_text("previous")
    before = tree(tmp_path)
    with (
        pytest.raises(OutputError, match=f"^{out}: no space left"),
        ResultDir(out, record={"name": "t"}) as tmp,
    ):
        (tmp / "a.txt").write_text("new")
        _enospc()
    assert tree(tmp_path) == before


def test_dataset_build_full_disk_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from scanguard.dataset import tasks
    from tests.test_hostile_data import fake_simulate, sim_config

    monkeypatch.setattr(tasks, "_simulate", fake_simulate)
    cfg = tmp_path / "c.yaml"
    sim_config().save(cfg)
    real = h5py.File

    def full(path: Any, mode: str = "r", *a: Any, **k: Any) -> Any:
        if mode != "r":
            raise OSError("Unable to synchronously create file (errno = 28, No space left)")
        return real(path, mode, *a, **k)

    monkeypatch.setattr(h5py, "File", full)
    res = invoke("dataset", "build", "-c", cfg, "-o", tmp_path / "b", "-j", "1")
    line = one_line_error(res, "no space left")
    assert ".h5" in line and res.output.count("error") == 1


def test_errors_cross_processes() -> None:
    for exc in (OutputError("a/b", "full"), FormatError("x.log", "bad", location="line 3")):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is type(exc) and str(back) == str(exc)


# --- hostile model files (defects 12 and 19) --------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value", "needle"),
    [
        ("version", "abc", "checkpoint version 'abc' is not a whole number"),
        ("version", [1], "checkpoint version [1] is not a whole number"),
        ("style", "paper", "checkpoint 'style' 'paper' is not a mapping"),
        ("style", 5, "checkpoint 'style' 5 is not a mapping"),
        ("style", {"kind": "nope"}, "invalid render style in checkpoint"),
        ("label_thresholds", "abc", "'label_thresholds' 'abc' is not a mapping"),
        ("label_thresholds", {"fault_translation": -1}, "label_thresholds"),
    ],
)
def test_hostile_checkpoint_fields(tmp_path: Path, field: str, value: Any, needle: str) -> None:
    ckpt = torch.load(MODELS / "default.pt", map_location="cpu", weights_only=True)
    ckpt[field] = value
    p = tmp_path / "bad.pt"
    torch.save(ckpt, p)
    with pytest.raises(ModelError) as info:
        load_checkpoint(p)
    text = str(info.value)
    assert text.startswith(f"{p}: ") and needle in text and "\n" not in text


def _baseline(tmp_path: Path, **changes: Any) -> Path:
    det = ThresholdDetector("mean_residual", "high", name="residual")
    p = save_detector(det, tmp_path / "b.json")
    data = json.loads(p.read_text())
    data.update({"threshold": 0.5, **changes})
    p.write_text(json.dumps(data))
    return p


def test_hostile_baseline_files(tmp_path: Path) -> None:
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000)
    with pytest.raises(ModelError, match=r"deep\.json: not valid JSON"):
        load_detector(deep)
    p = _baseline(tmp_path, type="metrics-model", kind="logistic", features="mean_residual")
    with pytest.raises(ModelError, match="features must be a list of feature names, not a str"):
        load_detector(p)
    blob = base64.b64encode(pickle.dumps(42)).decode()
    p = _baseline(
        tmp_path,
        type="metrics-model",
        kind="logistic",
        features=["mean_residual"],
        model_pickle=blob,
    )
    # any pickled model entry is refused before it is unpickled (version-free models only)
    with pytest.raises(ModelError, match="the model is a pickled scikit-learn estimator"):
        load_detector(p)
    p = _baseline(
        tmp_path, type="metrics-model", kind="logistic", features=["a"], model_pickle="!!"
    )
    with pytest.raises(ModelError, match="the model is a pickled scikit-learn estimator"):
        load_detector(p)


def test_deep_closure_judge_and_manifest(tmp_path: Path) -> None:
    p = tmp_path / "judge.json"
    p.write_text("{" + '"a":{' * 100_000)
    with pytest.raises(ModelError, match=r"judge\.json: not valid JSON"):
        load_closure_judge(p)
    d = tmp_path / "ds"
    d.mkdir()
    (d / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError, match=r"manifest\.json: not valid JSON"):
        PairStore.open(d)


# --- run-many's results.md (defect 20) --------------------------------------------------------


def test_results_md_cells_stay_in_their_row(tmp_path: Path) -> None:
    rows = [{"name": "a\nb|c\r\nd", "x": 1.0}, {"name": "plain\\", "x": 2.0}]
    _, md = write_table(rows, ["name", "x"], tmp_path, title="t", note="n")
    table = [ln for ln in md.read_text().splitlines() if ln.startswith("|")]
    assert len(table) == 2 + len(rows)
    assert table[2] == "| a b\\|c d | 1 |"
    assert md_cell("x\x00y\u2028z") == "x y z"


def test_deep_meta_json_in_a_shard(tmp_path: Path) -> None:
    paths = write_two(tmp_path)
    with h5py.File(paths[0], "r+") as f:
        f.attrs["meta_json"] = "[" * 100_000
    with pytest.raises(InputError, match=r"room_00\.h5: not valid JSON \(nested deeper"):
        PairStore.open(paths)
