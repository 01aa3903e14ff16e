"""`scanguard info`: figures in the table, one clear line and exit 1 on bad input."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from scanguard.cli import app

DATA = Path(__file__).resolve().parent / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
runner = CliRunner()


def _info(*args: str):
    return runner.invoke(app, ["info", *args], terminal_width=200)


def test_info_carmen_excerpt():
    res = _info(str(DATA / "intel-corrected-excerpt.log.gz"))
    assert res.exit_code == 0, res.output
    out = res.output
    assert "│ scans         │ 100" in out
    assert "│ beams         │ 180" in out
    assert "180.0 deg" in out
    assert "0.01 .. 80.00 m" in out
    assert "corrected_log" in out
    assert "FLASER" in out and "ODOM" in out


def test_info_bag_excerpt_with_static_reference():
    res = _info(str(DATA / "ccny-excerpt.bag"), "--reference", "static", "--scan-topic", "scan")
    assert res.exit_code == 0, res.output
    assert "│ scans         │ 60" in res.output
    assert "681" in res.output and "239.1 deg" in res.output and "5.60 m" in res.output
    assert "yes (static: static)" in res.output
    assert "/scan" in res.output and "sensor_msgs/msg/LaserScan" in res.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.bag"], "missing.bag: file not found"),
        (["{data}/README.md"], "unknown file extension '.md'"),
        (["{data}/ccny-excerpt.bag", "--scan-topic", "/nope"], "topic /nope: no LaserScan topic"),
        (["{data}/ccny-excerpt.bag", "--format", "velodyne"], "unknown format 'velodyne'"),
    ],
)
def test_info_errors_are_one_line(args, message):
    res = _info(*[a.format(data=DATA) for a in args])
    assert res.exit_code == 1
    text = res.output.strip()
    assert text.startswith("error:") and message in text
    assert "Traceback" not in text and len(text.splitlines()) == 1


@pytest.mark.skipif(not SHARED.exists(), reason="shared data not present")
@pytest.mark.parametrize(
    ("rel", "figures"),
    [
        ("rosbag/ccny_laser_scan_matcher_demo.bag", ["│ scans         │ 360", "681", "239.1 deg"]),
        (
            "carmen/intel-corrected.log.gz",
            ["│ scans         │ 910", "│ beams         │ 180", "180.0"],
        ),
    ],
)
def test_info_shared_files(rel, figures):
    res = _info(str(SHARED / rel))
    assert res.exit_code == 0, res.output
    for f in figures:
        assert f in res.output
