"""`scanguard.apps.replay` and ``run --realtime``: a recording at its sensor's rate."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from scanguard.apps.replay import (
    RecordingTransport,
    decisions_csv,
    replay,
    run_realtime,
)
from scanguard.cli import app
from scanguard.errors import ConfigError
from scanguard.slam.config import RunConfig
from tests.helpers import make_sequence, room_segments
from tests.test_run import AlignmentDetector

DATA = Path(__file__).parent / "data"


class SlowDetector(AlignmentDetector):
    """Takes ``seconds`` per judged pair: longer than the scans' spacing, so the node lags."""

    def __init__(self, seconds: float) -> None:
        super().__init__()
        self.seconds = seconds

    def fault_probability(self, previous, current, pose) -> float:
        time.sleep(self.seconds)
        return super().fault_probability(previous, current, pose)


@pytest.fixture(scope="module")
def room():
    return make_sequence(room_segments(), np.tile([0.05, 0.0, 0.02], (7, 1)))


def test_the_transport_answers_from_the_recording():
    stamps = np.array([0.0, 0.1, 0.1, 0.3])
    odom = np.arange(12, dtype=np.float64).reshape(4, 3)
    t = RecordingTransport(stamps, odom, np.array([0.2, 0.0, 0.0]))
    np.testing.assert_array_equal(t.odometry(0.3, 1.0), odom[3])
    np.testing.assert_array_equal(t.odometry(0.1, 1.0), odom[1])  # the first of a repeated stamp
    assert t.odometry(0.2, 1.0) is None  # no scan there
    np.testing.assert_array_equal(t.laser_offset("laser", 0.0, 1.0), [0.2, 0.0, 0.0])
    assert RecordingTransport(stamps, None, np.zeros(3)).odometry(0.0, 1.0) is None


def test_a_replay_that_keeps_up_processes_every_scan_in_order(room):
    cfg = RunConfig(backend="frontend")
    _, res = replay(room, cfg, AlignmentDetector(), None, None, rate=1.0)
    s = res.stats
    assert s["received"] == len(room)
    assert s["processed"] + s["dropped"] == len(room)
    # the loop is built on the first scan: nothing is dropped before it is processed
    assert [d["stamp"] for d in res.decisions] == res.stamps.tolist()
    assert res.trajectory.shape == (s["processed"], 3)
    assert s["latency_ms"]["max"] >= s["latency_ms"]["median"] > 0
    # played at the sensor's rate: the wall time is at least the recording's span
    assert res.wall_seconds >= res.log_seconds == pytest.approx(0.7, abs=1e-9)  # 7 steps, 10 Hz
    assert res.odometry is False and res.rate == 1.0


def test_a_node_slower_than_the_sensor_drops_scans_and_says_so(room, tmp_path):
    cfg = RunConfig(backend="frontend")
    res = run_realtime(room, SlowDetector(0.25), tmp_path, config=cfg, rate=1.0)
    s = res.stats
    # 0.25 s per judged pair against 0.1 s between scans and a queue of one: scans must go
    assert s["dropped"] >= 1
    assert s["processed"] + s["dropped"] == s["received"] == len(room)
    # the latency includes the wait in the queue: at least the step of the scan ahead
    assert s["latency_ms"]["max"] >= 250.0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["realtime"]["dropped"] == s["dropped"]
    assert metrics["realtime"]["latency_ms"]["p99"] == pytest.approx(s["latency_ms"]["p99"])
    # the reference of the processed scans scores the live trajectory
    assert 0.0 <= metrics["errors"]["ate_m"] < 0.05
    summary = (tmp_path / "summary.md").read_text()
    assert f"| {len(room)} | {s['processed']} | {s['dropped']} |" in summary
    rows = (tmp_path / "decisions.csv").read_text().splitlines()
    assert rows[0].startswith("index,stamp,accepted") and len(rows) == 1 + s["processed"]
    traj = np.loadtxt(tmp_path / "trajectory.tum")
    assert traj.shape == (s["processed"], 8)
    assert {p.name for p in res.files} >= {"map.pgm", "node.json", "metrics.json", "summary.md"}


def test_bad_rates_are_refused(room):
    for rate in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match="rate"):
            replay(room, RunConfig(backend="frontend"), AlignmentDetector(), None, None, rate=rate)


def test_decisions_csv_keeps_its_columns():
    text = decisions_csv([{"index": 3, "stamp": 1.5, "accepted": True, "extra": 1}])
    assert text.splitlines()[1].startswith("3,1.5,True,")
    assert "extra" not in text


def test_run_realtime_on_a_bag(tmp_path):
    out = tmp_path / "rt"
    args = ["run", str(DATA / "ccny-excerpt.bag"), "-o", str(out), "--realtime"]
    result = CliRunner().invoke(app, [*args, "--backend", "frontend", "--max-scans", "12"])
    assert result.exit_code == 0, result.output
    assert "at the sensor's rate" in result.output
    m = json.loads((out / "metrics.json").read_text())["realtime"]
    assert m["received"] == 12 and m["processed"] + m["dropped"] == 12
    assert m["odometry"] is False


def test_run_realtime_refuses_what_it_cannot_do(tmp_path):
    args = ["run", str(DATA / "ccny-excerpt.bag"), "-o", str(tmp_path / "x"), "--realtime"]
    result = CliRunner().invoke(app, [*args, "--mcap"])
    assert result.exit_code != 0
    assert "--realtime does not go with --mcap" in result.output
    assert not (tmp_path / "x").exists()


def test_scans_keep_their_spacing_and_a_stamp_that_steps_back_comes_at_once():
    from scanguard.apps.replay import offer_times

    stamps = np.array([10.0, 10.2, 10.4, 9.7, 9.9, 10.1])  # a logger wrote 9.7 late
    np.testing.assert_allclose(offer_times(stamps), [0.0, 0.2, 0.4, 0.4, 0.6, 0.8])
    np.testing.assert_allclose(offer_times(stamps, rate=2.0), [0.0, 0.1, 0.2, 0.2, 0.3, 0.4])
