"""``result.mcap`` and the live view, read back with independent readers.

The MCAP file is read with the ``mcap`` and ``mcap-ros2-support`` packages (not with
scanguard's reader); the live view is read with a plain ``websockets`` client speaking the
Foxglove WebSocket protocol. Their content must equal what the run wrote in its other files.
"""

from __future__ import annotations

import asyncio
import csv
import json
import struct
import threading
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scanguard.apps.demo import demo_sequence
from scanguard.apps.run import run_recording
from scanguard.apps.viz_sink import ViewOptions, VizSink, open_view
from scanguard.io.tum import read_tum
from scanguard.slam.config import RunConfig
from scanguard.slam.grid import PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN, read_pgm

mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

FRONTEND = RunConfig(backend="frontend")
#: Topic tag -> file tag of each instance.
INSTANCES = {"unguarded": "_unguarded", "cnn": "", "oracle": "_oracle_gate"}


class EveryThirdDetector:
    """A stand-in CNN: every third judged pair is a fault (probability 0.9), the rest 0.1."""

    threshold = 0.5

    def __init__(self) -> None:
        self.calls = 0

    def fault_probability(self, previous: Any, current: Any, pose: Any) -> float:
        self.calls += 1
        return 0.9 if self.calls % 3 == 0 else 0.1


@pytest.fixture(scope="module")
def demo_seq():
    return demo_sequence(fast=True, seed=3)  # the demo's scene, as `scanguard demo --fast`


@pytest.fixture(scope="module")
def mcap_run(demo_seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("view") / "run"
    out.mkdir()
    with open_view(ViewOptions(mcap=True, map_interval=1.0), out) as sink:
        res = run_recording(demo_seq, EveryThirdDetector(), out, config=FRONTEND, observer=sink)
    return out, res


def _read(path: Path) -> tuple[Counter[str], dict[str, list[Any]]]:
    """Message counts per topic and every message, ROS 2 ones decoded by mcap-ros2-support."""
    counts: Counter[str] = Counter()
    messages: dict[str, list[Any]] = {}
    factory = mcap_ros2_decoder.DecoderFactory()
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f)
        decoders: dict[int, Any] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            counts[channel.topic] += 1
            if channel.message_encoding == "json":
                value = json.loads(message.data)
            else:
                if schema.id not in decoders:
                    decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
                value = decoders[schema.id](message.data)
            messages.setdefault(channel.topic, []).append((message.log_time, value))
    return counts, messages


def test_mcap_counts_match_the_decisions(mcap_run, demo_seq):
    out, _ = mcap_run
    counts, messages = _read(out / "result.mcap")
    rows = list(csv.DictReader((out / "decisions.csv").open()))
    n = len(demo_seq)
    assert len(rows) == n
    reasons = Counter(r["reason"] for r in rows)
    rejected = sum(v for k, v in reasons.items() if k.startswith("rejected"))
    assert rejected >= 3  # the stand-in rejects every third pair: the test has something to see
    assert counts["/scan"] == n and counts["/tf"] == n and counts["/tf_static"] == 1
    assert counts["/scanguard/scan_accepted"] == reasons["first"] + reasons["accepted"]
    assert counts["/scanguard/scan_rejected"] == rejected + reasons["match_failed"]
    assert counts["/scanguard/decision"] == n - 1 - reasons["skipped"]
    assert counts["/scanguard/rejected_pair"] == rejected
    assert counts["/scanguard/reference/path"] == 1
    # a frame every second of log time (3 s recording) and the final one
    for tag in ("unguarded", "cnn"):
        assert counts[f"/scanguard/{tag}/map"] == counts[f"/scanguard/{tag}/path"] >= 4
    # the other instances: their final map only
    assert counts["/scanguard/oracle/map"] == 1 and counts["/scanguard/oracle/path"] >= 4
    # the decisions carry decisions.csv's values, at the scans' stamps
    by_index = {r["index"]: r for r in rows}
    for ns, d in messages["/scanguard/decision"]:
        row = by_index[str(d["index"])]
        assert d["reason"] == row["reason"] and int(d["accepted"]) == int(row["accepted"])
        assert f"{d['fault_probability']:.6g}" == row["fault_probability"]
        assert (d["motion_sources"] or "") == row["motion_sources"]
        if d["wheels_flagged"] is not None:
            assert int(d["wheels_flagged"]) == int(row["wheels_flagged"])
        assert abs(ns * 1e-9 - float(row["stamp"])) < 1e-6
        if d["reference_label"] is not None:
            assert d["reference_label"] == int(row["label"])
    # the rejected pairs are PNG images
    _, img = messages["/scanguard/rejected_pair"][0]
    assert img.format == "png" and bytes(img.data[:8]) == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(("tag", "pgm"), [("unguarded", "map_unguarded"), ("cnn", "map")])
def test_mcap_last_map_equals_the_pgm(mcap_run, tag, pgm):
    import yaml

    out, _ = mcap_run
    _, messages = _read(out / "result.mcap")
    _, grid = messages[f"/scanguard/{tag}/map"][-1]
    cells = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    image = read_pgm(out / f"{pgm}.pgm")[::-1]  # PGM: top row = largest y
    assert cells.shape == image.shape
    expected = np.select(
        [image == PGM_OCCUPIED, image == PGM_FREE, image == PGM_UNKNOWN], [100, 0, -1], 99
    )
    assert np.array_equal(cells, expected)
    assert (cells == 100).sum() > 100 and (cells == 0).sum() > 1000  # a real map
    meta = yaml.safe_load((out / f"{pgm}.yaml").read_text())
    assert grid.info.resolution == pytest.approx(meta["resolution"])
    origin = grid.info.origin.position
    assert [origin.x, origin.y] == pytest.approx(meta["origin"][:2], abs=1e-9)


@pytest.mark.parametrize("tag", INSTANCES)
def test_mcap_last_path_equals_the_tum_file(mcap_run, tag):
    out, _ = mcap_run
    _, messages = _read(out / "result.mcap")
    _, path = messages[f"/scanguard/{tag}/path"][-1]
    stamps, poses = read_tum(out / f"trajectory{INSTANCES[tag]}.tum")
    assert len(path.poses) == len(stamps)
    last = path.poses[-1]
    t = last.header.stamp.sec + 1e-9 * last.header.stamp.nanosec
    assert t == pytest.approx(stamps[-1], abs=1e-6)
    q = last.pose.orientation
    assert [last.pose.position.x, last.pose.position.y] == pytest.approx(poses[-1][:2], abs=1e-12)
    yaw = 2.0 * np.arctan2(q.z, q.w)
    assert np.angle(np.exp(1j * (yaw - poses[-1][2]))) == pytest.approx(0.0, abs=1e-9)


def test_default_run_writes_no_mcap_and_the_same_numbers(mcap_run, demo_seq, tmp_path):
    out, res = mcap_run
    plain = run_recording(demo_seq, EveryThirdDetector(), tmp_path / "plain", config=FRONTEND)
    assert not (tmp_path / "plain" / "result.mcap").exists()
    for name, traj in plain.trajectories.items():
        assert np.array_equal(traj, res.trajectories[name])
    a = (tmp_path / "plain" / "decisions.csv").read_text().splitlines()
    b = (out / "decisions.csv").read_text().splitlines()
    # the timing columns (from the 13th on) differ from run to run
    assert [r.split(",")[:12] for r in a] == [r.split(",")[:12] for r in b]


def test_failed_run_leaves_no_mcap(demo_seq, tmp_path):
    class Boom(EveryThirdDetector):
        def fault_probability(self, previous: Any, current: Any, pose: Any) -> float:
            if self.calls >= 5:
                raise KeyboardInterrupt
            return super().fault_probability(previous, current, pose)

    with (
        pytest.raises(KeyboardInterrupt),
        open_view(ViewOptions(mcap=True), tmp_path) as sink,
    ):
        run_recording(demo_seq, Boom(), tmp_path, config=FRONTEND, observer=sink)
    assert list(tmp_path.iterdir()) == []


# --- the live view -------------------------------------------------------------------------


class _WaitForClient:
    """Holds the run after `begin` (channels advertised) until the client has subscribed."""

    def __init__(self, sink: VizSink, ready: threading.Event) -> None:
        self.sink, self.ready = sink, ready

    def begin(self, seq: Any, names: Any) -> None:
        self.sink.begin(seq, names)
        assert self.ready.wait(20.0), "the client did not subscribe"

    def step(self, view: Any) -> None:
        self.sink.step(view)

    def end(self, trajectories: Any, grids: Any) -> None:
        self.sink.end(trajectories, grids)


async def _first_map_message(port: int, ready: threading.Event) -> tuple[dict[str, Any], bytes]:
    import websockets

    uri = f"ws://127.0.0.1:{port}"
    # foxglove-sdk >= 0.2x speaks foxglove.sdk.v1 (the successor of foxglove.websocket.v1)
    protocols = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
    async with websockets.connect(uri, subprotocols=protocols) as ws:  # type: ignore[arg-type]
        assert ws.subprotocol in protocols
        channel = None
        while channel is None:
            msg = json.loads(await ws.recv())
            if msg["op"] == "advertise":
                maps = [c for c in msg["channels"] if c["topic"] == "/scanguard/cnn/map"]
                channel = maps[0] if maps else None
        sub = {"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel["id"]}]}
        await ws.send(json.dumps(sub))
        await asyncio.sleep(0.2)  # the server registers the subscription
        ready.set()
        while True:
            data = await ws.recv()
            if isinstance(data, bytes) and data[0] == 0x01:  # message data
                return channel, data


def test_live_view_streams_the_map(demo_seq, tmp_path):
    pytest.importorskip("foxglove")
    pytest.importorskip("websockets")
    from mcap_ros2.decoder import DecoderFactory

    ready = threading.Event()
    failure: list[BaseException] = []
    with open_view(ViewOptions(live=True, port=0), tmp_path) as sink:
        assert sink is not None
        live = sink.outputs[0]
        port = live.port
        assert live.host == "127.0.0.1" and port > 0

        def run() -> None:
            try:
                observer = _WaitForClient(sink, ready)
                run_recording(demo_seq, EveryThirdDetector(), tmp_path, config=FRONTEND,
                              observer=observer)  # fmt: skip
            except BaseException as exc:  # reported by the test below
                failure.append(exc)

        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        channel, data = asyncio.run(asyncio.wait_for(_first_map_message(port, ready), 30.0))
        worker.join(60.0)
    assert not failure, failure
    assert channel["encoding"] == "cdr" and channel["schemaName"] == "nav_msgs/msg/OccupancyGrid"
    sub_id, ns = struct.unpack_from("<IQ", data, 1)
    assert sub_id == 7 and abs(ns * 1e-9 - demo_seq.stamps[0]) < 1e-6  # the recording's clock

    class Schema:
        name, encoding = channel["schemaName"], channel["schemaEncoding"]
        data = channel["schema"].encode()
        id = 1

    grid = DecoderFactory().decoder_for("cdr", Schema)(data[13:])
    assert grid.info.width > 0 and len(grid.data) == grid.info.width * grid.info.height
    assert {-1, 0, 100} >= set(np.unique(np.asarray(grid.data)).tolist())


def test_live_without_the_extra_names_it(monkeypatch):
    import builtins

    from scanguard.errors import ConfigError

    real_import = builtins.__import__

    def no_foxglove(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "foxglove" or name.startswith("foxglove."):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_foxglove)
    with pytest.raises(ConfigError, match=r"scanguard\[viz\]"):
        ViewOptions(live=True).check()


# --- the command line ---------------------------------------------------------------------

DATA = Path(__file__).resolve().parent / "data"


def _shipped_model() -> bool:
    from scanguard.detect.detector import default_model_path

    return default_model_path().exists()


@pytest.mark.skipif(not _shipped_model(), reason="the shipped model is not there")
def test_run_command_mcap_is_part_of_the_result(tmp_path):
    from typer.testing import CliRunner

    from scanguard.cli import app
    from scanguard.fsutil import read_marker

    out = tmp_path / "run"
    args = ["run", str(DATA / "intel-corrected-excerpt.log.gz"), "-o", str(out), "--mcap"]
    args += ["--backend", "frontend", "--max-scans", "12", "--baseline", "none"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    counts, messages = _read(out / "result.mcap")
    assert counts["/scan"] == 12 and counts["/scanguard/decision"] == 11
    marker = read_marker(out)
    assert marker is not None and "result.mcap" in marker["files"]
    _, path = messages["/scanguard/cnn/path"][-1]
    _, poses = read_tum(out / "trajectory.tum")
    assert path.poses[-1].pose.position.x == pytest.approx(poses[-1][0], abs=1e-12)


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--port", "70000"], "--port must be <= 65535"),
        (["--map-interval", "-1"], "--map-interval must be >= 0"),
    ],
)
def test_view_option_errors_are_one_line(option, message, tmp_path):
    from typer.testing import CliRunner

    from scanguard.cli import app

    result = CliRunner().invoke(app, ["demo", "--fast", "-o", str(tmp_path / "d"), *option])
    assert result.exit_code == 1
    text = result.output.strip()
    assert text.startswith("error:") and message in text and len(text.splitlines()) == 1


def test_live_command_without_the_extra_is_one_line(monkeypatch, tmp_path):
    from typer.testing import CliRunner

    from scanguard.apps import live_sink
    from scanguard.cli import app
    from scanguard.errors import ConfigError

    def missing() -> None:
        raise ConfigError(live_sink.VIZ_MISSING)

    monkeypatch.setattr(live_sink, "import_foxglove", missing)
    result = CliRunner().invoke(app, ["demo", "--fast", "--live", "-o", str(tmp_path / "d")])
    assert result.exit_code == 1
    assert result.output.strip() == f"error: {live_sink.VIZ_MISSING}"
    assert not (tmp_path / "d").exists()  # refused before any work


def test_layout_shows_topics_the_run_writes(mcap_run):
    out, _ = mcap_run
    counts, _ = _read(out / "result.mcap")
    layout = json.loads(
        (Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json").read_text()
    )
    panels = layout["configById"]
    topics = set(panels["3D!scanguard-map"]["topics"])
    topics.add(panels["Image!scanguard-pairs"]["imageMode"]["imageTopic"])
    topics |= {p["value"].split(".")[0] for p in panels["Plot!scanguard-decisions"]["paths"]}
    # the baseline instance is not in this run (no classical detector given)
    assert topics - set(counts) <= {"/scanguard/baseline/path"}
    assert {"/scanguard/cnn/map", "/scanguard/scan_rejected", "/scanguard/decision"} <= topics
    for node in ("first", "second"):
        assert node in layout["layout"]
