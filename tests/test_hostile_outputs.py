"""Hostile suite, third audit (issue 32, item 2): nothing lost, nothing written elsewhere.

Every case reproduces one of the audit's: a destination that is not scanguard's (a user's
folder with a ``results.csv``, an existing ``.onnx`` or picture, a link), a name from an input
that would become a path (a recording named ``..clf``, an environment named ``../``). The
answer is one line ``error: <file>: ...`` (exit 1) with every file as it was, or the result
where it belongs.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import h5py
import pytest

from scanguard.fsutil import MARKER, read_marker
from tests.test_dataset import write_two
from tests.test_hostile_cli import LOG, FakeLoop, invoke, leftovers, no_long_work, one_line_error

__all__ = ["no_long_work"]  # a fixture used by name below


def tree(root: Path) -> dict[str, bytes]:
    """Every regular file under ``root`` with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def fake_loop(monkeypatch: pytest.MonkeyPatch) -> FakeLoop:
    """`FakeLoop` whose result has a readable ``metrics.json`` (run-many reads it back)."""
    loop = FakeLoop(monkeypatch)
    loop.extra = {"metrics.json": '{"n_scans": 3}'}
    return loop


def run_many_args(spec: Path | str, out: Path) -> list[str]:
    return ["run-many", str(spec), "-o", str(out), "--backend", "frontend", "--baseline", "none"]


# --- 1: run-many never writes into a folder it did not create, nor outside its own ---------


def test_run_many_refuses_a_users_folder_with_results_csv(tmp_path: Path, monkeypatch) -> None:
    loop = fake_loop(monkeypatch)
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(LOG, src / LOG.name)
    user = tmp_path / "mine"
    user.mkdir()
    (user / "results.csv").write_text("my,own\n1,2\n")
    before = tree(tmp_path)
    line = one_line_error(invoke(*run_many_args(src, user)), "mine", "--overwrite")
    assert "not written by scanguard" in line
    assert loop.calls == 0 and tree(tmp_path) == before
    # with --overwrite it is written (the user's other files kept), and a rerun resumes
    (user / "notes.txt").write_text("keep me")
    res = invoke(*run_many_args(src, user), "--overwrite")
    assert res.exit_code == 0, res.output
    assert (user / "results.csv").read_text().startswith("recording,")
    assert (user / "notes.txt").read_text() == "keep me"
    marker = read_marker(user)
    assert marker is not None and marker["complete"] is True
    assert marker["name"] == "scanguard run-many" and "results.csv" in marker["files"]
    res = invoke(*run_many_args(src, user))
    assert res.exit_code == 0 and "resumed" in res.output, res.output
    assert loop.calls == 1
    # another command's result is not taken over either
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / MARKER).write_text('{"complete": true, "name": "scanguard train"}')
    one_line_error(invoke(*run_many_args(src, tmp_path / "other")), "`scanguard train`")


@pytest.mark.parametrize("name", ["...clf", ".clf", "..clf", "results.csv.clf", "RESULTS.MD.clf"])
def test_run_many_recording_names_never_become_paths(
    name: str, tmp_path: Path, monkeypatch
) -> None:
    loop = fake_loop(monkeypatch)
    src = tmp_path / "in"
    src.mkdir()
    rec = src / name
    rec.write_bytes(LOG.read_bytes())
    out = tmp_path / "box" / "out"
    before = tree(tmp_path)
    line = one_line_error(invoke(*run_many_args(rec, out)), name)
    assert "result folder name" in line and "rename the input" in line
    assert loop.calls == 0 and tree(tmp_path) == before and not (tmp_path / "box").exists()


def test_run_many_folder_search_skips_hidden_files_and_refuses_table_names(
    tmp_path: Path, monkeypatch
) -> None:
    fake_loop(monkeypatch)
    src = tmp_path / "in"
    src.mkdir()
    for name in ("..clf", ".clf", "...clf"):
        (src / name).write_bytes(b"hidden: never a result folder")
    shutil.copy(LOG, src / LOG.name)
    out = tmp_path / "out"
    res = invoke(*run_many_args(src, out))
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [MARKER, "results.csv", "results.md", "intel-corrected-excerpt"]
    )
    assert not (tmp_path / "results.csv").exists() and leftovers(tmp_path) == []
    (src / "results.csv.clf").write_bytes(b"x")
    before = tree(tmp_path)
    one_line_error(invoke(*run_many_args(src, out)), "results.csv.clf", "table files")
    assert tree(tmp_path) == before


def test_evaluate_per_store_refuses_a_users_folder(tmp_path: Path) -> None:
    paths = write_two(tmp_path / "src")
    user = tmp_path / "mine"
    user.mkdir()
    (user / "results.csv").write_text("mine\n")
    args = ["evaluate", "--per-store", "-d", str(paths[0]), "-o", str(user), "--baselines", "none"]
    one_line_error(invoke(*args), "mine", "not written by scanguard", "--overwrite")
    assert (user / "results.csv").read_text() == "mine\n"


# --- 2: names inside a pair store never become paths either -----------------------------------


@pytest.mark.parametrize("attr", ["environment", "sequence"])
def test_export_png_store_names_cannot_leave_the_output(attr: str, tmp_path: Path) -> None:
    paths = write_two(tmp_path / "a" / "src")
    with h5py.File(paths[0], "r+") as f:
        f.attrs[attr] = "../../../escaped"
    out = tmp_path / "a" / "out"
    before = tree(tmp_path)
    line = one_line_error(invoke("dataset", "export-png", *paths, "-o", out), "room_00.h5")
    assert attr in line and "cannot be a file name" in line
    assert tree(tmp_path) == before and not out.exists()
    assert not list(tmp_path.rglob("*.png"))


# --- 3: dataset stats writes its folder as a whole ---------------------------------------------


def test_dataset_stats_keeps_a_users_stats_json(tmp_path: Path) -> None:
    paths = write_two(tmp_path / "src")
    user = tmp_path / "mine"
    user.mkdir()
    (user / "stats.json").write_text("my numbers")
    one_line_error(invoke("dataset", "stats", *paths, "-o", user), "mine", "--overwrite")
    assert tree(user) == {"stats.json": b"my numbers"}
    res = invoke("dataset", "stats", *paths, "-o", user, "--overwrite")
    assert res.exit_code == 0, res.output
    assert (user / "stats.json").read_text().startswith("[")
    # its own result is replaced by a rerun, and the default folder needs no option
    assert invoke("dataset", "stats", *paths, "-o", user).exit_code == 0
    assert invoke("dataset", "stats", *paths).exit_code == 0
    assert (tmp_path / "src" / "stats" / "stats.json").is_file()


# --- 4: one-file outputs: an existing file or a link is replaced only with --overwrite ---------


def test_export_onnx_keeps_an_existing_file_and_a_link(tmp_path: Path, no_long_work) -> None:
    existing = tmp_path / "model.onnx"
    existing.write_bytes(b"precious")
    one_line_error(invoke("export", "onnx", "-o", existing), "model.onnx", "exists", "--overwrite")
    target = tmp_path / "elsewhere.txt"
    target.write_text("not a model")
    link = tmp_path / "link.onnx"
    link.symlink_to(target)
    one_line_error(invoke("export", "onnx", "-o", link), "link.onnx", "--overwrite")
    dangling = tmp_path / "dangling.onnx"
    dangling.symlink_to(tmp_path / "made.onnx")
    one_line_error(invoke("export", "onnx", "-o", dangling), "dangling", "symbolic link")
    assert existing.read_bytes() == b"precious" and target.read_text() == "not a model"
    assert not (tmp_path / "made.onnx").exists()


def test_export_onnx_overwrite_replaces_the_file(tmp_path: Path) -> None:
    existing = tmp_path / "model.onnx"
    existing.write_bytes(b"old")
    res = invoke("export", "onnx", "-o", existing, "--overwrite")
    assert res.exit_code == 0, res.output
    assert existing.stat().st_size > 1000


def test_simulate_preview_keeps_an_existing_picture(tmp_path: Path, no_long_work) -> None:
    png = tmp_path / "world.png"
    png.write_bytes(b"\x89PNG my holiday picture")
    args: list[Any] = ["simulate", "--duration", "5", "--preview", png]
    one_line_error(invoke(*args), "world.png", "exists", "--overwrite")
    assert png.read_bytes() == b"\x89PNG my holiday picture"
    assert sorted(os.listdir(tmp_path)) == ["world.png"]


# --- 5: every command that reads a recording applies the one input-path check -----------------


@pytest.mark.parametrize("command", ["calibrate", "dataset build"])
@pytest.mark.parametrize("special", ["fifo", "/dev/zero"])
def test_special_recordings_never_block(command: str, special: str, tmp_path: Path) -> None:
    import subprocess
    import sys
    import time

    path = tmp_path / "x.log" if special == "fifo" else Path(special)
    if special == "fifo":
        os.mkfifo(path)
    words = command.split()
    script = "import sys; sys.argv[0] = 'scanguard'; from scanguard.cli import app; app()"
    args = [*words, "-r", str(path), "--reference", "static", "-o", str(tmp_path / "out")]
    t0 = time.perf_counter()
    # in a subprocess: before the fix this blocks forever (FIFO) or hashes without end
    proc = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=120
    )
    text = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 1 and "Traceback" not in text, text
    assert text.splitlines()[-1].startswith("error:") and str(path) in text.splitlines()[-1]
    assert "not a regular file" in text and time.perf_counter() - t0 < 60
    assert not (tmp_path / "out").exists()


# --- 18: a full numba cache is named as such, never blamed on the output ------------------------


def test_full_numba_cache_names_the_cache_not_the_output(tmp_path: Path, monkeypatch) -> None:
    import errno

    import numba
    from numba.core import caching

    from scanguard.cli.main import os_error_text
    from scanguard.errors import OutputError
    from scanguard.fsutil import ResultDir

    cache = tmp_path / "numba-cache"
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(cache))

    def full(self: Any, filepath: str) -> Any:  # numba's writer on a full disk: no file name
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(caching.IndexDataCacheFile, "_open_for_write", full)
    src = tmp_path / "kernel_mod.py"  # a fresh kernel, so that numba compiles and saves it
    src.write_text("import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import kernel_mod  # type: ignore[import-not-found]

    out = tmp_path / "out"
    with pytest.raises(OutputError) as info, ResultDir(out) as tmp:
        (tmp / "a.txt").write_text("x")
        kernel_mod.twice(3)
    text = str(info.value)
    assert "numba cache folder" in text and "NUMBA_CACHE_DIR" in text
    assert not text.startswith(str(out)) and not out.exists()
    with pytest.raises(OSError) as raw:
        kernel_mod.twice(4.5)  # a new signature: compiled and saved again
    assert "numba cache folder" in os_error_text(raw.value)


# --- 6: a live-view client that connects and never reads ------------------------------------------


def _silent_client(port: int) -> Any:
    """A Foxglove WebSocket client that subscribes to the first channel, then never reads."""
    import base64
    import json
    import socket
    import struct

    def frame(text: bytes) -> bytes:  # a masked client text frame
        mask = os.urandom(4)
        size = (
            bytes([0x80 | len(text)]) if len(text) < 126 else b"\xfe" + struct.pack(">H", len(text))
        )
        return b"\x81" + size + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(text))

    def read(sock: Any, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            assert chunk, "server closed"
            data += chunk
        return data

    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        f"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
        "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n".encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += read(sock, 1)
    assert b" 101 " in head.split(b"\r\n")[0], head
    while True:
        b0, b1 = read(sock, 2)
        n = b1 & 0x7F
        n = struct.unpack(">H", read(sock, 2))[0] if n == 126 else n
        n = struct.unpack(">Q", read(sock, 8))[0] if n == 127 else n
        data = read(sock, n)
        if b0 & 0x0F == 1 and json.loads(data).get("op") == "advertise":
            channel = json.loads(data)["channels"][0]["id"]
            break
    sub = {"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel}]}
    sock.sendall(frame(json.dumps(sub).encode()))
    return sock


def test_live_view_with_a_client_that_never_reads_stops_in_time() -> None:
    pytest.importorskip("foxglove")
    import threading
    import time

    from scanguard.apps.live_sink import STOP_TIMEOUT, LiveOutput
    from scanguard.apps.viz_messages import ChannelSpec

    live = LiveOutput("127.0.0.1", 0)
    live.__enter__()
    sock = None
    try:
        live.add_channel(ChannelSpec("/big", "std_msgs/String", "ros2msg", b"string data", "cdr"))
        sock = _silent_client(live.port)
        time.sleep(0.3)  # the subscription reaches the server
        payload = b"x" * 1_000_000
        t0 = time.perf_counter()
        for i in range(200):  # far more than the client's socket takes: queued, then dropped
            live.write("/big", payload, i)
        assert time.perf_counter() - t0 < 10
    finally:
        stopper = threading.Thread(target=live.__exit__, args=(None, None, None), daemon=True)
        t0 = time.perf_counter()
        stopper.start()
        stopper.join(STOP_TIMEOUT + 8)
    # before the fix the SDK's stop waited for the client for ever (and no signal got in)
    assert not stopper.is_alive() and time.perf_counter() - t0 < STOP_TIMEOUT + 2
    if sock is not None:
        sock.close()
