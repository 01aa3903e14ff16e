"""Hostile-input suite, CLI side (issue 11): the output layer and the error boundary.

Every case of the issue that the CLI owns is here: special files and symbolic links as
outputs, unwritable and wrong-kind destinations, result folders written as a whole (a killed
rerun, a failed run, a user's folder), stale temporaries, Ctrl-C, bounds on options, and
output that stays readable without a wide terminal. The heavy parts of a run (model, SLAM
loop) are replaced by small fakes so that the suite stays fast; `tests/test_run.py` runs the
real loop through the same code.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import stat
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from typer.testing import CliRunner

from scanguard.cli import app
from scanguard.errors import ConfigError, InputError, OutputError
from scanguard.fsutil import (
    MARKER,
    ResultDir,
    atomic_write_text,
    check_output_path,
    clean_stale_temporaries,
    is_complete_result,
    read_marker,
)

DATA = Path(__file__).resolve().parent / "data"
LOG = DATA / "intel-corrected-excerpt.log.gz"
runner = CliRunner()


def invoke(*args: str) -> Any:
    return runner.invoke(app, [str(a) for a in args])


def one_line_error(result: Any, *needles: str, code: int = 1) -> str:
    """Assert the one-line ``error: ...`` contract; return the line."""
    text = result.output.strip()
    assert result.exit_code == code, result.output
    assert "Traceback" not in text, text
    lines = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, text
    assert text.splitlines()[-1] == lines[0], text  # the error is the last line, whole
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def dead_pid() -> int:
    """The id of a process that has exited."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def leftovers(folder: Path) -> list[str]:
    """Temporaries of scanguard in ``folder`` (names with ``.sg<pid>-``)."""
    return sorted(p.name for p in folder.iterdir() if ".sg" in p.name and p.name[0] == ".")


# --- a fast stand-in for the guarded SLAM loop ------------------------------------------------


class FakeLoop:
    """Replaces the model loading and `run_recording`; writes a small result into ``out``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, tag: str = "run1") -> None:
        import scanguard.apps.run as run_mod
        import scanguard.cli.run as run_cli
        import scanguard.detect.detector as detector

        self.tag = tag
        self.fail: BaseException | None = None
        self.extra: dict[str, str] = {}
        self.calls = 0
        monkeypatch.setattr(detector.FaultDetector, "load", classmethod(lambda *a, **k: object()))
        monkeypatch.setattr(run_mod, "run_recording", self)
        monkeypatch.setattr(run_cli, "_pipeline_report", lambda res, out: None)

    def __call__(self, seq: Any, det: Any, out: Path, **kw: Any) -> Any:
        self.calls += 1
        out = Path(out)
        files = []
        for name in ("config.yaml", "decisions.csv", "summary.md", "metrics.json"):
            (out / name).write_text(f"{self.tag} {name}\n")
            files.append(out / name)
            if self.fail is not None and name == "decisions.csv":
                raise self.fail
        for name, text in self.extra.items():
            (out / name).write_text(text)
        return SimpleNamespace(files=files, relations={})


def run_args(out: Path, *extra: str) -> list[str]:
    return ["run", str(LOG), "-o", str(out), "--backend", "frontend", "--baseline", "none", *extra]


# --- 1: special files and links are never replaced --------------------------------------------


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    p = tmp_path / "pipe.onnx"
    os.mkfifo(p)
    return p


def test_char_device_is_refused_and_kept() -> None:
    r = invoke("export", "onnx", "-o", "/dev/null")
    one_line_error(r, "/dev/null", "character device")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    with pytest.raises(OutputError, match="character device"):
        atomic_write_text("/dev/null", "x")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize("command", ["export", "simulate", "run"])
def test_fifo_is_refused_and_kept(command: str, fifo: Path, tmp_path: Path) -> None:
    args = {
        "export": ["export", "onnx", "-o", fifo],
        "simulate": ["simulate", "--duration", "1", "-o", fifo],
        "run": run_args(fifo),
    }[command]
    one_line_error(invoke(*args), str(fifo), "FIFO")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert leftovers(tmp_path) == []


def test_link_to_a_device_is_refused(tmp_path: Path) -> None:
    link = tmp_path / "model.onnx"
    link.symlink_to("/dev/null")
    one_line_error(invoke("export", "onnx", "-o", link), "model.onnx", "character device")
    assert link.is_symlink() and stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_symbolic_links_are_followed_not_replaced(tmp_path: Path, monkeypatch) -> None:
    target = tmp_path / "real.txt"
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target.name)
    atomic_write_text(link, "new")
    assert link.is_symlink() and os.readlink(link) == "real.txt"
    assert target.read_text() == "new"
    # a dangling link: its target is created
    dangling = tmp_path / "dangling.txt"
    dangling.symlink_to("made.txt")
    atomic_write_text(dangling, "made")
    assert dangling.is_symlink() and (tmp_path / "made.txt").read_text() == "made"
    # a result folder behind a link: written in the target folder, the link kept
    real_dir = tmp_path / "runs-real"
    link_dir = tmp_path / "runs"
    link_dir.symlink_to(real_dir.name)
    FakeLoop(monkeypatch)
    assert invoke(*run_args(link_dir)).exit_code == 0
    assert link_dir.is_symlink() and (real_dir / "summary.md").is_file()
    assert is_complete_result(real_dir)


# --- 14, 15, 16: unwritable and wrong-kind outputs are one line, before any work ---------------


@pytest.fixture
def no_long_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any long work reached before the output check fails the test loudly."""
    import scanguard.apps.demo as demo_mod
    import scanguard.detect.detector as detector
    import scanguard.io as io
    import scanguard.sim as sim

    def boom(*a: Any, **k: Any) -> Any:
        raise AssertionError("long work started before the output was checked")

    monkeypatch.setattr(io, "read_sequence", boom)
    monkeypatch.setattr(sim, "simulate_run", boom)
    monkeypatch.setattr(demo_mod, "demo_sequence", boom)
    monkeypatch.setattr(detector.FaultDetector, "load", classmethod(boom))


def _commands(out: str) -> dict[str, list[str]]:
    return {
        "export onnx": ["export", "onnx", "-o", f"{out}.onnx"],
        "simulate": ["simulate", "--duration", "5", "-o", f"{out}.mcap"],
        "simulate bag folder": ["simulate", "--duration", "5", "-o", out],
        "simulate --preview": ["simulate", "--duration", "5", "--preview", f"{out}.png"],
        "run": run_args(Path(out)),
        "demo": ["demo", "--fast", "-o", out],
        "dataset build": ["dataset", "build", "-r", str(LOG), "-o", out],
        "dataset merge": ["dataset", "merge", "missing-store", "-o", out],
        "dataset export-png": ["dataset", "export-png", "missing-store", "-o", out],
        "train": ["train", "-d", "missing-store", "-o", out],
        "evaluate": ["evaluate", "-d", "missing-store", "-o", out],
    }


COMMANDS = list(_commands("x"))


@pytest.mark.parametrize("command", COMMANDS)
def test_output_under_a_regular_file(command: str, tmp_path: Path, no_long_work) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("mine")
    out = str(blocker / "sub" / "out")
    one_line_error(invoke(*_commands(out)[command]), "a-file", "not a directory")
    assert blocker.read_text() == "mine"


@pytest.mark.parametrize("command", COMMANDS)
def test_unwritable_output(command: str, no_long_work) -> None:
    # as root, permissions do not stop a write: /proc refuses new files to everyone
    out = "/proc/scanguard-hostile/out"
    one_line_error(invoke(*_commands(out)[command]), "/proc/scanguard-hostile", "cannot write")


@pytest.mark.parametrize("command", ["run", "demo", "dataset build", "train", "evaluate"])
def test_folder_output_that_is_a_file(command: str, tmp_path: Path, no_long_work) -> None:
    existing = tmp_path / "taken"
    existing.write_text("mine")
    one_line_error(invoke(*_commands(str(existing))[command]), "taken", "expected a folder")
    assert existing.read_text() == "mine"


def test_file_output_that_is_a_folder(tmp_path: Path, no_long_work) -> None:
    (tmp_path / "m.onnx").mkdir()
    one_line_error(invoke("export", "onnx", "-o", tmp_path / "m.onnx"), "m.onnx", "directory")
    (tmp_path / "p.png").mkdir()
    r = invoke("simulate", "--duration", "5", "--preview", tmp_path / "p.png")
    one_line_error(r, "p.png", "directory")


def test_simulate_output_suffix_makes_no_stray_folder(tmp_path: Path, no_long_work) -> None:
    # item 35: `-o out.txt` is neither a .mcap file nor a bag folder name
    r = invoke("simulate", "--duration", "5", "-o", tmp_path / "out.txt")
    one_line_error(r, "out.txt", "'.txt'", ".mcap")
    assert not (tmp_path / "out.txt").exists()


@pytest.mark.parametrize(
    ("exc", "needle"),
    [
        (OSError(errno.ENOSPC, "No space left on device", "/data/run/map.pgm"), "no space left"),
        (PermissionError(errno.EACCES, "Permission denied", "/data/x.onnx"), "permission denied"),
        (FileExistsError(errno.EEXIST, "File exists", "/data/x"), "already exists"),
        (IsADirectoryError(errno.EISDIR, "Is a directory", "/data/x"), "is a directory"),
        (NotADirectoryError(errno.ENOTDIR, "Not a directory", "/data/x/y"), "not a directory"),
        (OSError(errno.EROFS, "Read-only file system", "/data/x"), "read-only file system"),
    ],
)
def test_os_errors_are_one_line_naming_the_path(exc, needle, tmp_path: Path, monkeypatch) -> None:
    import scanguard.detect.detector as detector

    def fail(*a: Any, **k: Any) -> Any:
        raise exc

    monkeypatch.setattr(detector.FaultDetector, "load", classmethod(fail))
    r = invoke("export", "onnx", "-o", tmp_path / "x.onnx")
    one_line_error(r, f"error: {exc.filename}: {needle}")
    assert not (tmp_path / "x.onnx").exists() and leftovers(tmp_path) == []


def test_out_of_memory_is_one_line(tmp_path: Path, monkeypatch) -> None:
    import scanguard.detect.detector as detector

    def fail(*a: Any, **k: Any) -> Any:
        raise MemoryError("Unable to allocate 224. GiB")

    monkeypatch.setattr(detector.FaultDetector, "load", classmethod(fail))
    one_line_error(invoke("export", "onnx", "-o", tmp_path / "x.onnx"), "out of memory", "224")


def test_error_text_is_escaped_onto_one_line(tmp_path: Path, monkeypatch) -> None:
    import scanguard.detect.detector as detector

    def fail(*a: Any, **k: Any) -> Any:
        raise InputError("x.pt", "bad [bold]bytes[/bold] \x1b[31m\nsecond line\x00")

    monkeypatch.setattr(detector.FaultDetector, "load", classmethod(fail))
    line = one_line_error(invoke("export", "onnx", "-o", tmp_path / "x.onnx"), "x.pt")
    assert "\x1b" not in line and "\x00" not in line
    assert "\\x1b[31m" in line and "\\nsecond line" in line and "[bold]bytes[/bold]" in line


# --- 6, 11, 35: result folders are written as a whole ----------------------------------------


def test_users_folder_is_refused_without_overwrite(tmp_path: Path, monkeypatch) -> None:
    loop = FakeLoop(monkeypatch)
    user = tmp_path / "mine"
    user.mkdir()
    (user / "summary.md").write_text("my own notes")
    (user / "config.yaml").write_text("my: config\n")
    r = invoke(*run_args(user))
    one_line_error(r, "mine", "not written by scanguard", MARKER, "--overwrite")
    assert loop.calls == 0  # refused before any work
    assert (user / "summary.md").read_text() == "my own notes"
    assert sorted(p.name for p in user.iterdir()) == ["config.yaml", "summary.md"]
    assert leftovers(tmp_path) == []
    # --overwrite replaces scanguard's files only; the user's other files stay
    (user / "notes.txt").write_text("keep me")
    r = invoke(*run_args(user, "--overwrite"))
    assert r.exit_code == 0, r.output
    assert (user / "summary.md").read_text() == "run1 summary.md\n"
    assert (user / "notes.txt").read_text() == "keep me"
    marker = read_marker(user)
    assert marker is not None and marker["complete"] is True
    assert "notes.txt" not in marker["files"] and "summary.md" in marker["files"]
    assert leftovers(tmp_path) == []


def test_empty_folder_is_used(tmp_path: Path, monkeypatch) -> None:
    FakeLoop(monkeypatch)
    (tmp_path / "empty").mkdir()
    assert invoke(*run_args(tmp_path / "empty")).exit_code == 0
    assert is_complete_result(tmp_path / "empty")


def test_rerun_replaces_a_result_as_a_whole(tmp_path: Path, monkeypatch) -> None:
    loop = FakeLoop(monkeypatch)
    out = tmp_path / "r"
    loop.extra = {"only-in-run1.txt": "x"}
    assert invoke(*run_args(out)).exit_code == 0
    loop.tag, loop.extra = "run2", {}
    r = invoke(*run_args(out, "--seed", "3"))
    assert r.exit_code == 0, r.output
    assert (out / "summary.md").read_text() == "run2 summary.md\n"
    assert not (out / "only-in-run1.txt").exists()
    marker = read_marker(out)
    assert marker is not None and "--seed 3" in marker["command"]
    assert leftovers(tmp_path) == []


def test_marker_records_the_full_command_line(tmp_path: Path, monkeypatch) -> None:
    FakeLoop(monkeypatch)
    out = tmp_path / "r"
    model = tmp_path / "m.pt"
    r = invoke(*run_args(out, "--model", str(model), "--reference", "static", "--max-scans", "5"))
    assert r.exit_code == 0, r.output
    marker = read_marker(out)
    assert marker is not None
    cmd = marker["command"]
    assert cmd.startswith("scanguard run ") and str(LOG) in cmd
    for part in (f"--model {model}", "--baseline none", "--reference static", "--max-scans 5"):
        assert part in cmd, cmd
    assert marker["options"]["runtime"] == "onnx"  # defaults are recorded too
    assert marker["scanguard"] and marker["started"] and marker["finished"]
    assert set(marker["files"]) == {"config.yaml", "decisions.csv", "summary.md", "metrics.json"}


@pytest.mark.parametrize("how", ["keyboard", "numba"])
def test_killed_rerun_keeps_the_previous_result_whole(how: str, tmp_path: Path, monkeypatch):
    loop = FakeLoop(monkeypatch)
    out = tmp_path / "r"
    assert invoke(*run_args(out)).exit_code == 0
    before = {p.name: p.read_text() for p in out.iterdir()}
    loop.tag = "run2"
    if how == "keyboard":
        loop.fail = KeyboardInterrupt()
    else:  # item 23: what numba raises when Ctrl-C hits a compiled loop
        try:
            raise SystemError(
                "CPUDispatcher(<function icp_loop>) returned a result with an exception set"
            ) from KeyboardInterrupt()
        except SystemError as exc:
            loop.fail = exc
    r = invoke(*run_args(out))
    assert r.exit_code == 130, r.output
    assert "interrupted" in r.output and "Traceback" not in r.output
    assert {p.name: p.read_text() for p in out.iterdir()} == before  # nothing mixed
    assert leftovers(tmp_path) == []


def test_failed_run_leaves_no_stub(tmp_path: Path, monkeypatch) -> None:
    loop = FakeLoop(monkeypatch)
    loop.fail = InputError("other.relations", "no relation matches a scan stamp")
    out = tmp_path / "new" / "deep" / "r"
    r = invoke(*run_args(out))
    one_line_error(r, "other.relations")
    assert not (tmp_path / "new").exists()  # neither the folder nor the parents made for it
    assert leftovers(tmp_path) == []


def test_run_recording_writes_nothing_before_the_end(tmp_path: Path) -> None:
    # the library too: a run that fails half-way leaves no folder holding a config alone
    from scanguard.apps.run import run_recording
    from scanguard.slam.config import RunConfig
    from tests.helpers import make_sequence, room_segments

    class Boom:
        threshold = 0.5

        def fault_probability(self, *a: Any) -> float:
            raise InputError(None, "detector failed")

    import numpy as np

    seq = make_sequence(room_segments(), np.tile([0.06, 0.01, 0.02], (3, 1)))
    with pytest.raises(InputError):
        run_recording(seq, Boom(), tmp_path / "r", config=RunConfig(backend="frontend"))
    assert not (tmp_path / "r").exists()


def test_strict_json_has_no_bare_nan() -> None:
    import numpy as np

    from scanguard.apps.run_report import strict_json

    text = strict_json({"a": float("nan"), "b": [np.float64("inf"), 1.5], "c": np.int64(3)})
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in JSON"))
    assert data == {"a": None, "b": [None, 1.5], "c": 3}


# --- 12: temporaries of a killed write are removed by the next one ----------------------------


def test_stale_temporaries_are_cleaned(tmp_path: Path, monkeypatch) -> None:
    pid = dead_pid()
    stale_dir = tmp_path / f".r.sg{pid}-abcdefgh.partial"
    stale_dir.mkdir()
    (stale_dir / "decisions.csv").write_text("half")
    stale_file = tmp_path / f".x.onnx.sg{pid}-abcdefgh.onnx"
    stale_file.write_text("half")
    live = tmp_path / f".x.onnx.sg{os.getpid()}-abcdefgh.onnx"  # a write in progress
    live.write_text("busy")
    FakeLoop(monkeypatch)
    assert invoke(*run_args(tmp_path / "r")).exit_code == 0
    assert not stale_dir.exists()
    atomic_write_text(tmp_path / "x.onnx", "done")
    assert not stale_file.exists() and live.exists()
    assert (tmp_path / "x.onnx").read_text() == "done"


def test_result_moved_aside_by_a_killed_swap_is_restored(tmp_path: Path) -> None:
    aside = tmp_path / f".r.sg{dead_pid()}-abcdefgh.old"
    aside.mkdir()
    (aside / "summary.md").write_text("previous")
    assert clean_stale_temporaries(tmp_path) == [tmp_path / "r"]
    assert (tmp_path / "r" / "summary.md").read_text() == "previous"


# --- 23: Ctrl-C ---------------------------------------------------------------------------------


def test_ctrl_c_is_exit_130_and_nothing_half_written(tmp_path: Path, monkeypatch) -> None:
    loop = FakeLoop(monkeypatch)
    loop.fail = KeyboardInterrupt()
    r = invoke(*run_args(tmp_path / "r"))
    assert r.exit_code == 130 and "interrupted" in r.output
    assert list(tmp_path.iterdir()) == []


def test_interrupt_wrapped_in_an_error_is_130(tmp_path: Path, monkeypatch) -> None:
    loop = FakeLoop(monkeypatch)
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as ki:
        loop.fail = InputError("x", "read failed")
        loop.fail.__context__ = ki
    assert invoke(*run_args(tmp_path / "r")).exit_code == 130


class SignalLoop(FakeLoop):
    """A loop that receives a real signal half-way (``how`` says where and which)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, how: str) -> None:
        super().__init__(monkeypatch)
        self.how = how
        self.survived = False

    def __call__(self, seq: Any, det: Any, out: Path, **kw: Any) -> Any:
        import signal
        import time

        (Path(out) / "decisions.csv").write_text("half")
        if self.how == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
        elif self.how == "swallowed":  # numba: the interrupt is lost, another error follows
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.5)
            except KeyboardInterrupt:
                pass
            raise RuntimeError("no compiled object yet for <Library 'run'>")
        elif self.how == "llvm":  # arrives inside an LLVM callback: deferred, then raised
            code = "import os, signal\nos.kill(os.getpid(), signal.SIGINT)\nx = sum(range(99))"
            exec(compile(code, "/site-packages/llvmlite/binding/fake.py", "exec"), {})
            self.survived = True
        else:
            os.kill(os.getpid(), signal.SIGINT)
        time.sleep(2)
        raise AssertionError("the signal did not stop the command")


@pytest.mark.parametrize(("how", "code"), [("sigint", 130), ("swallowed", 130), ("llvm", 130)])
def test_real_signals_end_the_command_cleanly(how, code, tmp_path: Path, monkeypatch) -> None:
    import signal

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("another SIGINT handler is installed")
    loop = SignalLoop(monkeypatch, how)
    r = invoke(*run_args(tmp_path / "r"))
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output and list(tmp_path.iterdir()) == []
    assert loop.survived == (how == "llvm")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def test_sigterm_is_exit_143_and_nothing_half_written(tmp_path: Path, monkeypatch) -> None:
    import signal

    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        pytest.skip("another SIGTERM handler is installed")
    SignalLoop(monkeypatch, "sigterm")
    r = invoke(*run_args(tmp_path / "r"))
    assert r.exit_code == 143 and "terminated" in r.output
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


# --- 17, 18, 25, 35: bounds on options, before any work --------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["simulate", "--seed", "-1", "-o", "{tmp}/s.mcap"], "--seed must be >= 0, got -1"),
        (["demo", "--seed", "-1", "-o", "{tmp}/d"], "--seed must be >= 0, got -1"),
        (["run", str(LOG), "--seed", "-1", "-o", "{tmp}/r"], "--seed must be >= 0"),
        (["simulate", "--duration", "inf", "-o", "{tmp}/s.mcap"], "--duration must be a finite"),
        (["simulate", "--duration", "nan", "-o", "{tmp}/s.mcap"], "--duration is not a number"),
        (["simulate", "--duration", "-3", "-o", "{tmp}/s.mcap"], "--duration must be > 0"),
        (["simulate", "--duration", "0", "-o", "{tmp}/s.mcap"], "--duration must be > 0"),
        (["simulate", "--scan-rate", "0", "-o", "{tmp}/s.mcap"], "--scan-rate must be > 0"),
        (["simulate", "--stride", "0", "-o", "{tmp}/s.mcap"], "--stride must be >= 1"),
        (["simulate", "--people", "-2", "-o", "{tmp}/s.mcap"], "--people must be >= 0"),
        (["dataset", "export-png", "s", "-o", "{tmp}/p", "-n", "-5"], "--per-class must be >= 1"),
        (["dataset", "export-png", "s", "-o", "{tmp}/p", "--seed", "-1"], "--seed must be >= 0"),
        (["dataset", "build", "-r", "x.log", "-o", "{tmp}/b", "-j", "0"], "--workers must be"),
        (["train", "-d", "s", "-o", "{tmp}/t", "--epochs", "0"], "--epochs must be >= 1"),
        (["train", "-d", "s", "-o", "{tmp}/t", "--threads", "-1"], "--threads must be >= 1"),
    ],
)
def test_bad_numbers_are_one_line(args, message, tmp_path: Path, no_long_work) -> None:
    r = invoke(*[a.format(tmp=tmp_path) for a in args])
    one_line_error(r, message)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("where", ["option", "config"])
def test_unknown_matcher_is_rejected_before_the_model(where, tmp_path: Path, no_long_work):
    extra = ["--matcher", "nope"]
    if where == "config":
        cfg = tmp_path / "run.yaml"
        cfg.write_text("matcher: nope\n")
        extra = ["--config", str(cfg)]
    one_line_error(invoke(*run_args(tmp_path / "r", *extra)), "unknown matcher 'nope'")
    assert not (tmp_path / "r").exists()


# --- confusing messages -----------------------------------------------------------------------


def test_odom_topic_on_a_corrected_log_is_not_ignored(tmp_path: Path, monkeypatch) -> None:
    loop = FakeLoop(monkeypatch)
    r = invoke(*run_args(tmp_path / "r", "--odom-topic", "ODOM"))
    one_line_error(r, "--odom-topic ODOM", "corrected log")
    assert loop.calls == 0 and not (tmp_path / "r").exists()
    r = invoke(*run_args(tmp_path / "r", "--odom-topic", "ODOM", "--odometry", "simulated"))
    one_line_error(r, "--odom-topic ODOM", "--odometry simulated")


def test_dataset_build_takes_the_topics_it_hints_at(tmp_path: Path, monkeypatch) -> None:
    # item 32: the readers suggest --scan-topic; dataset build must accept it
    import scanguard.dataset.build as build_mod

    seen: dict[str, Any] = {}

    def fake_build(
        paths: list[str],
        out: str,
        cfg: Any,
        *,
        reference: str | None = None,
        initial_guess: str | None = None,
        max_scans: int | None = None,
        overwrite: bool = False,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        reference_topic: str | None = None,
        executor: Any = None,
    ) -> Any:
        seen.update(paths=paths, scan_topic=scan_topic, odom_topic=odom_topic)
        return SimpleNamespace(
            built=list(paths), skipped=[], entries=[], totals=lambda: _zero(), failed={}
        )

    monkeypatch.setattr(build_mod, "build_from_recordings", fake_build)
    out = tmp_path / "b"
    r = invoke("dataset", "build", "-r", "a.bag", "-r", "b.bag", "-o", out, "--scan-topic", "/f")
    assert r.exit_code == 0, r.output
    assert seen == {"paths": ["a.bag", "b.bag"], "scan_topic": "/f", "odom_topic": None}
    assert "2 built, 0 resumed" in r.output  # item 31: every recording counted
    assert "--scan-topic" in invoke("dataset", "build", "--help").output


def _zero() -> dict[str, int]:
    return dict.fromkeys(("pairs", "normal", "fault", "ambiguous"), 0)


def test_evaluate_without_a_train_split_hints_at_the_options(tmp_path: Path, monkeypatch) -> None:
    import scanguard.detect.evaluate as ev

    def fail(*a: Any, **k: Any) -> Any:
        raise ConfigError("data/real: no labelled pairs in split(s) ['train']")

    monkeypatch.setattr(ev, "evaluate_store", fail)
    r = invoke("evaluate", "-d", "data/real", "-o", tmp_path / "ev")
    one_line_error(r, "no labelled pairs", "--baseline-data", "--baselines none")
    assert not (tmp_path / "ev").exists()


# --- output without a wide terminal -----------------------------------------------------------


def test_tables_fit_80_columns_without_truncation(tmp_path: Path, monkeypatch) -> None:
    import scanguard.detect.evaluate as ev

    row = {
        "method": "metrics-model",
        "environment": "environment-5-office",
        "TP": 1234,
        "FN": 56,
        "FP": 78,
        "TN": 9012,
        "recall": 0.9123,
        "precision": 0.8765,
        "accuracy": 0.9432,
        "f1": 0.8941,
        "auc": 0.9712,
        "threshold": 0.512,
        "n_ambiguous": 345,
        "ambiguous_flagged": 0.4321,
    }
    monkeypatch.setattr(ev, "evaluate_store", lambda *a, **k: SimpleNamespace(rows=[row]))
    r = invoke("evaluate", "-d", "store")
    assert r.exit_code == 0, r.output
    assert "…" not in r.output
    assert max(len(line) for line in r.output.splitlines()) <= 80
    flat = " ".join(r.output.split())
    for text in ("metrics-model", "1234", "9012", "91.2%", "0.971", "345 (43.2%)"):
        assert text in flat, text
    assert "environment-5-office" in r.output.replace("\n", "").replace(" ", "")


def test_progress_is_log_lines_without_a_terminal(caplog) -> None:
    from scanguard.logging_utils import progress

    with caplog.at_level(logging.INFO, logger="scanguard.progress"), progress(95, "render") as adv:
        for _ in range(95):
            adv(1, status="ok")
    lines = [r.getMessage() for r in caplog.records if r.name == "scanguard.progress"]
    assert 9 <= len(lines) <= 11
    assert lines[-1].startswith("render 95/95 (100 %), ok")
    assert all("\r" not in ln for ln in lines)


def test_log_lines_are_plain_without_a_terminal(tmp_path: Path, monkeypatch, capsys) -> None:
    from scanguard.logging_utils import configure_logging

    configure_logging()  # pytest's stderr is not a terminal
    long = "x" * 150
    logging.getLogger("scanguard.test").warning("a long line %s", long)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "scanguard.test" in ln]
    assert len(lines) == 1 and lines[0].endswith(f"WARNING scanguard.test: a long line {long}")


@pytest.mark.parametrize("command", [["run"], ["demo"], ["simulate"], ["dataset", "build"]])
def test_help_shows_flags_as_flags(command: list[str]) -> None:
    r = invoke(*command, "--help")
    assert r.exit_code == 0, r.output
    assert "<bool>" not in r.output
    assert "--help" in r.output
    if command in (["run"], ["demo"]):
        assert "--overwrite" in r.output


def test_check_output_path_contract(tmp_path: Path) -> None:
    assert check_output_path(tmp_path / "new" / "x.onnx", suffixes=(".onnx",)) == (
        tmp_path / "new" / "x.onnx"
    )
    assert not (tmp_path / "new").exists()  # checking creates nothing
    with pytest.raises(OutputError, match="unsupported extension"):
        check_output_path(tmp_path / "x.txt", "dir", suffixes=(".mcap", ""))
    with pytest.raises(OutputError, match="empty output path"):
        check_output_path("", "file")
    rd = ResultDir(tmp_path / "res", record={"command": "test"})
    with rd as tmp:
        (tmp / "sub").mkdir()
        (tmp / "sub" / "a.txt").write_text("a")
        assert rd.final(tmp / "sub" / "a.txt") == tmp_path / "res" / "sub" / "a.txt"
    marker = read_marker(tmp_path / "res")
    assert marker is not None and marker["files"] == ["sub/a.txt"]
    assert marker["command"] == "test"


def test_another_commands_result_is_never_wiped(tmp_path: Path) -> None:
    # `evaluate -o runs/x` into the folder of `train -o runs/x`: the model stays
    out = tmp_path / "x"
    with ResultDir(out, record={"name": "train"}) as tmp:
        (tmp / "model.pt").write_text("weights")
        (tmp / "history.json").write_text("{}")
    with ResultDir(out, record={"name": "evaluate"}) as tmp:
        (tmp / "results.json").write_text("{}")
    assert (out / "model.pt").read_text() == "weights" and (out / "results.json").is_file()
    marker = read_marker(out)
    assert marker is not None and marker["name"] == "evaluate"
    assert marker["files"] == ["results.json"]
    assert marker["other_files"] == ["history.json", "model.pt"]
    # the same command again replaces its own files only
    with ResultDir(out, record={"name": "evaluate"}) as tmp:
        (tmp / "results.csv").write_text("")
    assert not (out / "results.json").exists() and (out / "model.pt").is_file()
