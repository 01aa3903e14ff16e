"""Hostile suite, third audit (issue 32, item 2): values no run can mean.

Non-finite and absurd numbers in configs and options (``.inf``, ``.nan``, ``1e300``), stamps
that ROS time cannot hold, relations and scans that contradict themselves, sizes that would
exhaust memory, and calibration data that cannot determine a calibration. Each is refused in
one line naming the file or the option, before the run; none runs to a silently wrong figure.
"""

from __future__ import annotations

import gzip
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scanguard.errors import ConfigError
from tests.test_hostile_cli import LOG, invoke, no_long_work, one_line_error, run_args

__all__ = ["no_long_work"]  # a fixture used by name below


# --- 11, 12: configs: finite and bounded, at the config models --------------------------------


@pytest.mark.parametrize(
    ("yaml_text", "key", "problem"),
    [
        ("gmapping: {srr: .inf}", "gmapping.srr", "must be a finite number, got inf"),
        ("gmapping: {srr: .nan}", "gmapping.srr", "is not a number (nan)"),
        ("gmapping: {srr: 1.0e+300}", "gmapping.srr", "less than or equal to 10"),
        ("gmapping: {stt: -.inf}", "gmapping.stt", "must be a finite number, got -inf"),
        ("guard: {grid: {resolution: .inf}}", "guard.grid.resolution", "finite number"),
        ("guard: {grid: {resolution: 1.0e+9}}", "guard.grid.resolution", "less than or equal"),
        ("relation_tolerance: .nan", "relation_tolerance", "is not a number (nan)"),
    ],
)
def test_non_finite_and_huge_config_values_are_one_line(
    yaml_text: str, key: str, problem: str, tmp_path: Path, no_long_work
) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(yaml_text + "\n")
    one_line_error(invoke(*run_args(tmp_path / "out", "-c", cfg)), "bad.yaml", key, problem)
    assert not (tmp_path / "out").exists()


def test_every_config_model_refuses_non_finite_floats() -> None:
    from scanguard.dataset import DatasetConfig
    from scanguard.detect.train_config import TrainConfig
    from scanguard.slam.gmapping.config import GMappingConfig
    from scanguard.slam.grid import GridConfig

    for model, key in (
        (GMappingConfig, "srr"),
        (GridConfig, "resolution"),
        (GridConfig, "l_occ"),
        (DatasetConfig, "odometry_noise"),
        (TrainConfig, "lr"),
    ):
        for bad in (math.inf, math.nan):
            value = {"trans": bad} if key == "odometry_noise" else bad
            with pytest.raises(ConfigError, match=r"finite number|not a number"):
                model.from_dict({key: value}, source="t")


# --- 14, 20: options: finite, bounded, and NaN said to be NaN ---------------------------------


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("inf", "must be a finite number, got inf"),
        ("1e309", "must be a finite number, got inf"),
        ("nan", "is not a number (nan)"),
        ("11", "less than or equal to 10"),
    ],
)
def test_relation_tolerance_is_finite_and_bounded(
    value: str, problem: str, tmp_path: Path, no_long_work
) -> None:
    args = run_args(tmp_path / "out", "--relation-tolerance", value)
    one_line_error(invoke(*args), "relation_tolerance", problem)


def test_nan_option_is_not_a_number_not_a_bound(tmp_path: Path, no_long_work) -> None:
    args = run_args(tmp_path / "out", "--map-interval", "nan")
    line = one_line_error(invoke(*args), "--map-interval", "is not a number")
    assert ">=" not in line and ">" not in line.split("--map-interval")[1]


# --- 7: the view's path frames: packed once, bounded in size ------------------------------------


def test_path_frames_are_rosbags_bytes_without_a_message_object_per_pose(monkeypatch) -> None:
    from scanguard.apps.viz_messages import PATH, Encoder, stamp_ns

    enc = Encoder()
    rng = np.random.default_rng(7)
    n = 2000
    stamps = rng.uniform(0, 2e9, n)
    stamps[:2] = (-1.0, 1e9 + 0.9999999999)
    poses = rng.normal(size=(n, 3)) * 50
    poses[5, 1] = np.inf  # left out, as before
    fast = enc.path(stamps, poses, 123_456_789_012)
    # the reference: one rosbags message object per pose, serialised by rosbags
    T = enc.T
    items = [
        T["geometry_msgs/msg/PoseStamped"](
            header=enc._header(stamp_ns(t), "map"), pose=enc._pose(p)
        )
        for t, p in zip(stamps.tolist(), poses, strict=True)
        if np.all(np.isfinite(p))
    ]
    msg = T[PATH](header=enc._header(123_456_789_012, "map"), poses=items)
    assert fast == bytes(enc.ts.serialize_cdr(msg, PATH))
    # no Python object per pose any more (the quadratic part of a long --mcap run)
    built = {"n": 0}
    real = T["geometry_msgs/msg/PoseStamped"]

    def counting(*a: Any, **k: Any) -> Any:
        built["n"] += 1
        return real(*a, **k)

    monkeypatch.setitem(T, "geometry_msgs/msg/PoseStamped", counting)
    enc.path(np.arange(50_000) * 0.1, np.zeros((50_000, 3)), 0)
    assert built["n"] == 0


def test_path_frames_during_a_run_are_bounded() -> None:
    from scanguard.apps.viz_sink import PATH_FRAME_POSES, _Track, thin_indices

    for n in (0, 1, 5, PATH_FRAME_POSES, PATH_FRAME_POSES + 1, 20_000, 10**6):
        idx = thin_indices(n, PATH_FRAME_POSES)
        assert len(idx) <= PATH_FRAME_POSES and len(idx) == min(n, len(idx))
        if n:
            assert idx[0] == 0 and idx[-1] == n - 1 and np.all(np.diff(idx) > 0)
    track = _Track(3)
    for i in range(1000):
        track.append(np.array([i, -i, 0.5]))
    rows = track.rows()
    assert rows.shape == (1000, 3) and rows[999, 1] == -999


# --- 10, 17: stamps ROS time cannot hold ---------------------------------------------------------


def shifted_log(tmp_path: Path, offset: float) -> Path:
    """The test log with every stamp moved by ``offset`` seconds (CARMEN: the last 3 fields)."""
    out = tmp_path / f"shifted{offset:+.0f}.log"
    lines = []
    for line in gzip.decompress(LOG.read_bytes()).decode().splitlines():
        words = line.split()
        if words and words[0] in ("FLASER", "ODOM", "RLASER", "TRUEPOS", "ROBOTLASER1"):
            words[-3] = f"{float(words[-3]) + offset:.6f}"
            words[-1] = f"{float(words[-1]) + offset:.6f}"
        lines.append(" ".join(words))
    out.write_text("\n".join(lines) + "\n")
    return out


@pytest.mark.parametrize(("offset", "problem"), [(3e9, "reach 3"), (-1e6, "negative")])
def test_mcap_refuses_stamps_ros_time_cannot_hold(offset: float, problem: str, tmp_path: Path):
    log = shifted_log(tmp_path, offset)
    out = tmp_path / "out"
    args = ["run", log, "-o", out, "--backend", "frontend", "--baseline", "none", "--max-scans"]
    line = one_line_error(invoke(*args, "12", "--mcap"), log.name, problem, "ROS time")
    assert "struct" not in line and not out.exists()
    # without a view the run is fine: only ROS messages need ROS time
    assert invoke(*args, "12").exit_code == 0


# --- 19: the automatic relations look-up skips a name that cannot exist -----------------------


def test_long_recording_name_runs_without_a_relations_look_up_error(tmp_path: Path, monkeypatch):
    from tests.test_hostile_cli import FakeLoop

    FakeLoop(monkeypatch)
    name = "r" * (251 - len(".log")) + ".log"  # <stem>.relations: 257 characters, too long
    rec = tmp_path / name
    rec.write_bytes(gzip.decompress(LOG.read_bytes()))
    res = invoke(*run_args(tmp_path / "out")[:1], rec, *run_args(tmp_path / "out")[2:])
    assert res.exit_code == 0, res.output
    assert "file name too long" not in res.output


# --- 13: a LaserScan whose ranges disagree with its angle fields ---------------------------------


@pytest.mark.parametrize("writer", ["ros1", "ros2"])
def test_laserscan_with_inconsistent_beam_count_is_one_line(writer: str, tmp_path: Path) -> None:
    from scanguard.errors import FormatError
    from scanguard.io import read_sequence
    from tests import bagkit

    write = bagkit.write_ros1 if writer == "ros1" else bagkit.write_ros2
    name = "bad.bag" if writer == "ros1" else "bad"
    # 5 ranges, but -1.0 .. 1.0 rad at 0.1 rad make 21 beams: the angles would be wrong
    msgs = bagkit.scans(4, ranges=(2.0,) * 5, angle_min=-1.0, increment=0.1, angle_max=1.0)
    bag = write(tmp_path / name, msgs)
    with pytest.raises(FormatError) as err:
        read_sequence(bag)
    text = str(err.value)
    assert text.startswith(str(bag)) and "5 ranges" in text and "make 21 beams" in text
    assert "\n" not in text
    with pytest.raises(Exception, match="no usable messages"):
        read_sequence(bag, lenient=True)  # every message skipped, and said so
    # one beam more or less is how drivers differ: read as is
    ok = bagkit.scans(4, ranges=(2.0,) * 5, angle_min=-1.0, increment=0.1, angle_max=-0.5)
    assert len(read_sequence(write(tmp_path / f"ok{name}", ok))) == 4


# --- 15: the particle filter's memory is estimated before it allocates ----------------------------


def test_particles_beyond_the_memory_estimate_are_refused_up_front(
    tmp_path: Path, no_long_work
) -> None:
    from scanguard.slam.gmapping import _kernels
    from scanguard.slam.gmapping.config import PATCH_SIDE, GMappingConfig, estimated_map_bytes

    assert PATCH_SIDE == _kernels.PATCH  # the estimate follows the maps' layout
    args = run_args(tmp_path / "out", "--backend", "gmapping", "--particles", "10000")
    line = one_line_error(invoke(*args), "10000 particles need about 4.8 GiB", "--particles")
    assert "4 GiB limit" in line and not (tmp_path / "out").exists()
    # a smaller initial map leaves room for them; the default 30 particles are far below
    small = GMappingConfig(particles=10000, xmin=-20, xmax=20, ymin=-20, ymax=20)
    assert estimated_map_bytes(small) < 2**32
    assert estimated_map_bytes(GMappingConfig()) < 2**25
