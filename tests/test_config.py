from pathlib import Path

import pytest

from scanguard.config import YamlModel, save_config
from scanguard.errors import ConfigError
from scanguard.fsutil import atomic_path


class Demo(YamlModel):
    threshold: float = 0.1
    name: str = "x"


def test_yaml_round_trip(tmp_path: Path):
    cfg = Demo(threshold=0.25, name="lobby")
    p = save_config(cfg, tmp_path)
    assert Demo.from_yaml(p) == cfg


def test_bad_key_names_file_and_key(tmp_path: Path):
    p = tmp_path / "c.yaml"
    p.write_text("threshold: 0.1\nbogus: 3\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: bogus"):
        Demo.from_yaml(p)
    with pytest.raises(ConfigError, match="not found"):
        Demo.from_yaml(tmp_path / "missing.yaml")


def test_atomic_path_keeps_old_file_on_failure(tmp_path: Path):
    dest = tmp_path / "out.txt"
    dest.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(dest) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert dest.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_output_has_normal_permissions(tmp_path: Path):
    import os

    umask = os.umask(0o022)
    try:
        with atomic_path(tmp_path / "x.txt") as tmp:
            tmp.write_text("x")
    finally:
        os.umask(umask)
    assert (tmp_path / "x.txt").stat().st_mode & 0o777 == 0o644


def test_every_shipped_run_config_loads():
    from scanguard.slam.config import RunConfig

    files = sorted((Path(__file__).parents[1] / "configs").glob("run_*.yaml"))
    assert len(files) >= 6
    for path in files:
        RunConfig.from_yaml(path)  # raises on a field that does not exist or a bad value
    fast = RunConfig.from_yaml(files[0].parent / "run_fast.yaml")
    assert fast.graph.minimum_travel_distance == 0.2 and fast.backend == "graph"
