"""Hostile and careless input to the simulator and `scanguard simulate` (issue 11).

Every case fails fast with one ``error:`` line and exit code 1 (or a `ConfigError` /
`OutputError` from the library), before any simulation or large allocation; outputs are
streamed, checked before the run and written atomically.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from scanguard.cli import app
from scanguard.errors import ConfigError, OutputError, ScanGuardError
from scanguard.sim import (
    apply_overrides,
    load_scenario,
    parse_overrides,
    plan_simulation,
    simulate,
    simulate_run,
)
from scanguard.sim.limits import MEMORY_LIMIT_BYTES, format_bytes
from scanguard.sim.output import BagStreamWriter, check_bag_output

runner = CliRunner()


def _cli(*args: str, cwd: Path | None = None) -> Any:
    old = Path.cwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        return runner.invoke(app, ["simulate", *args], terminal_width=200)
    finally:
        os.chdir(old)


def _one_line_error(res: Any, *needles: str) -> str:
    """The error line of a failed command; checks exit 1, one line, no traceback."""
    assert res.exit_code == 1, res.output
    text = res.stderr.strip()
    assert "Traceback" not in res.output, res.output
    lines = text.splitlines()
    assert lines and lines[-1].startswith("error:"), text
    line = lines[-1]
    for needle in needles:
        assert needle in line, line
    return line


@pytest.fixture
def no_simulation(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if a simulation starts (the error must come before it)."""
    import scanguard.sim

    def boom(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the simulation started before the input was refused")

    monkeypatch.setattr(scanguard.sim, "simulate_run", boom)


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# --- item 17: seeds -------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [-1, -(2**70), 2**64, 1.5, True, "3"])
def test_library_rejects_bad_seeds(seed: Any) -> None:
    with pytest.raises(ConfigError, match="seed must be"):
        simulate("lobby", seed=seed, duration=0.1)


def test_negative_seed_message_and_demo_sequence() -> None:
    from scanguard.apps.demo import demo_sequence

    with pytest.raises(ConfigError, match=r"seed must be >= 0, got -1"):
        simulate_run("lobby", seed=-1, duration=0.1)
    with pytest.raises(ConfigError, match=r"seed must be >= 0"):
        demo_sequence(fast=True, seed=-1)


@pytest.mark.parametrize("command", ["simulate", "demo"])
def test_cli_negative_seed_is_one_line(command: str, tmp_path: Path, no_simulation: None) -> None:
    args = [command, "--seed", "-1"]
    if command == "simulate":
        args += ["-o", str(tmp_path / "a.mcap")]
    else:
        args += ["-o", str(tmp_path / "demo")]
    res = runner.invoke(app, args, terminal_width=200)
    _one_line_error(res, "seed", ">= 0")
    assert _leftovers(tmp_path) == []


# --- item 18: durations ---------------------------------------------------------------------


@pytest.mark.parametrize("duration", [float("inf"), float("-inf"), float("nan"), 0.0, -3.0])
def test_library_rejects_non_finite_and_non_positive_durations(duration: float) -> None:
    with pytest.raises(ConfigError, match="duration"):
        simulate("lobby", seed=0, duration=duration)


@pytest.mark.parametrize("duration", ["inf", "nan", "-inf", "0", "-1"])
def test_cli_bad_duration_is_one_line(duration: str, tmp_path: Path, no_simulation: None) -> None:
    res = _cli("--duration", duration, "-o", str(tmp_path / "a.mcap"))
    _one_line_error(res, "duration")
    assert _leftovers(tmp_path) == []


def test_huge_duration_is_refused_by_the_memory_estimate_before_allocating(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import scanguard.sim.engine as engine

    def no_world(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the world was built before the run was sized")

    monkeypatch.setattr(engine, "build_world", no_world)
    for keep in (True, False):
        with pytest.raises(ConfigError) as err:
            simulate_run("lobby", seed=0, duration=1e9, keep_scans=keep)
        msg = str(err.value)
        assert "needs about" in msg and "TiB" in msg and "--duration" in msg
        assert format_bytes(MEMORY_LIMIT_BYTES) in msg and "\n" not in msg
    with pytest.raises(ConfigError, match="needs about"):
        simulate_run("lobby", seed=0, duration=1e300)  # no OverflowError on the way


def test_cli_huge_duration_is_one_line(tmp_path: Path, no_simulation: None) -> None:
    t0 = time.monotonic()
    res = _cli("--duration", "1e9", "-o", str(tmp_path / "a.mcap"))
    _one_line_error(res, "needs about", "of memory", "--duration")
    assert time.monotonic() - t0 < 10
    assert _leftovers(tmp_path) == []


def test_plan_counts_match_the_run() -> None:
    cfg, seconds, plan = plan_simulation("corridor", duration=1.05, stride=2)
    res = simulate_run(cfg, seed=1, duration=seconds, people__count=2)
    assert (plan.n_scans, plan.n_kept) == (11, 6)
    assert res.n_kept == len(res.sequence) == plan.n_kept
    assert res.robot_path.shape[0] == plan.n_scans


# --- items 19 and 27: scenario values -------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        ({"world__params__width": [26, 18]}, "reversed"),
        ({"world__params__width": [-26, -18]}, "must lie within"),
        ({"world__params__width": -5}, "must lie within"),
        ({"world__params__width": 1e7}, "must lie within"),
        ({"world__params__width": float("nan")}, "not finite"),
        ({"world__params__depth": [1, float("inf")]}, "not finite"),
        ({"world__params__widht": 20}, "unknown parameter"),
        ({"world__params__width": "wide"}, "expected a number"),
        ({"world__params__width": [1, 2, 3]}, "expected a number"),
        ({"sensor__n_beams": 50_000_000}, "sensor.n_beams"),
        ({"sensor__range_max": 1e300}, "sensor.range_max"),
        ({"sensor__range_max": float("inf")}, "sensor.range_max"),
        ({"sensor__range_min": 30.0}, "range_min"),
        ({"sensor__rate_hz": 1e6}, "sensor.rate_hz"),
        ({"sensor__noise_std": float("nan")}, "sensor.noise_std"),
        ({"scan_rate_hz": 1_000_000}, "scan_rate_hz"),
        ({"scan_rate_hz": 1e-300}, "scan_rate_hz"),
        ({"physics_dt": 1e-12}, "physics_dt"),
        ({"stride": 10**9}, "stride"),
        ({"people__count": 10**6}, "people.count"),
        ({"people__speed": [2.0, 1.0]}, "speed"),
        ({"people__group_size": [0, 4]}, "group_size"),
        ({"people__body_radius": [0.2, 1e9]}, "body_radius"),
        ({"robot__max_speed": float("inf")}, "robot.max_speed"),
        ({"robot__cruise_speed": [1.2, 0.8]}, "cruise_speed"),
        ({"robot__laser_offset": [0, 0, float("nan")]}, "robot.laser_offset"),
        ({"odometry__scale_error": -1.0}, "odometry.scale_error"),
        ({"world__start": [1e300, 0, 0]}, "world.start"),
        ({"world__circles": [{"center": [0, 1e9], "radius": 1}]}, "world.circles"),
        ({"duration": float("inf")}, "duration"),
        ({"name": ""}, "name"),
    ],
)
def test_scenario_values_are_bounded(overrides: dict[str, Any], needle: str) -> None:
    with pytest.raises(ConfigError) as err:
        apply_overrides(load_scenario("lobby"), **overrides)
    msg = str(err.value)
    assert needle in msg and "\n" not in msg, msg
    assert msg.startswith("scenario 'lobby' overrides:")


def test_bad_scenario_file_names_the_file_and_key(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("name: bad\nworld: {generator: lobby}\nsensor: {n_beams: 50000000}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: sensor\.n_beams"):
        load_scenario(path)
    path.write_text("name: bad\nworld: {generator: lobby, params: {width: [26, 18]}}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: world: .*width \[26\.0, 18\.0\] is rev"):
        load_scenario(path)
    path.write_text("name: bad\nworld: {generator: lobby}\nsensor: {range_max: .inf}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: sensor\.range_max"):
        load_scenario(path)


@pytest.mark.parametrize(
    "args",
    [
        ["--set", "world.params.width=[26, 18]"],
        ["--set", "world.params.width=[-26, -18]"],
        ["--set", "sensor.n_beams=50000000"],
        ["--set", "sensor.range_max=1.0e300"],
        ["--set", "scan_rate_hz=1000000"],
        ["--scan-rate", "1000000"],
        ["--people", "1000000"],
        ["--set", "world.params.width=1.0e6"],
    ],
)
def test_cli_scenario_values_are_one_line(
    args: list[str], tmp_path: Path, no_simulation: None
) -> None:
    res = _cli("-d", "1", "-o", str(tmp_path / "a.mcap"), *args)
    _one_line_error(res)
    assert _leftovers(tmp_path) == []


def test_layouts_the_generator_cannot_build_are_config_errors() -> None:
    # within the bounds, but too small for the lobby's furniture
    with pytest.raises(ConfigError, match="cannot lay out"):
        simulate("lobby", seed=0, duration=0.1, world__params__width=5.0)


def test_world_too_large_for_the_navigation_grid_is_refused_before_allocating() -> None:
    with pytest.raises(ConfigError, match=r"navigation grid .* raise world\.grid_resolution"):
        simulate("lobby", seed=0, duration=0.1, world__params={"width": 1900, "depth": 1900})


def test_too_much_geometry_is_refused() -> None:
    zigzag = [[float(i % 2), i * 0.001] for i in range(60_000)]
    walls = [{"points": zigzag}, {"points": [[x + 5, y] for x, y in zigzag]}]
    with pytest.raises(ConfigError, match="more than the limit of 100,000"):
        simulate("lobby", seed=0, duration=0.1, world__walls=walls)


def test_work_limits_name_what_to_lower() -> None:
    # 0.1 Hz scans with 1 ms physics steps: 10,000 sub-steps per scan
    with pytest.raises(ConfigError, match=r"physics steps.*physics_dt"):
        plan_simulation("lobby", duration=100_000.0, scan_rate_hz=0.1, physics_dt=0.001)
    with pytest.raises(ConfigError, match=r"scans.*--duration"):
        plan_simulation("lobby", duration=1e6, scan_rate_hz=100, people__count=0, sensor__n_beams=2)


def test_numeric_fields_never_raise_anything_but_config_error() -> None:
    hypothesis = pytest.importorskip("hypothesis")
    st = hypothesis.strategies
    keys = [
        "scan_rate_hz", "stride", "physics_dt", "duration", "people__count", "people__speed",
        "people__pause_duration", "people__group_size", "sensor__n_beams", "sensor__fov_deg",
        "sensor__range_min", "sensor__range_max", "sensor__rate_hz", "robot__cruise_speed",
        "world__params__width", "world__params__depth", "world__params__pillars",
        "world__grid_resolution", "world__start", "materials__max_bounces",
    ]  # fmt: skip
    number = st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(min_value=-(2**80), max_value=2**80),
    )
    value = st.one_of(number, st.lists(number, max_size=4), st.text(max_size=5), st.none())
    base = load_scenario("lobby")

    @hypothesis.settings(max_examples=300, deadline=None, derandomize=True, database=None)
    @hypothesis.given(key=st.sampled_from(keys), val=value)
    def check(key: str, val: Any) -> None:
        try:
            cfg = apply_overrides(base, **{key: val})
            plan_simulation(cfg, duration=cfg.duration or 10.0)
        except ConfigError as exc:
            assert "\n" not in str(exc)

    check()


# --- item 20: --set with broken YAML --------------------------------------------------------


def test_set_with_broken_yaml_is_one_line(tmp_path: Path, no_simulation: None) -> None:
    res = _cli("-d", "1", "-o", str(tmp_path / "a.mcap"), "--set", "people={count: [1")
    line = _one_line_error(res, "invalid YAML in --set", "people={count: [1")
    assert "ParserError" not in line
    with pytest.raises(ConfigError, match="invalid YAML in --set"):
        parse_overrides(["sensor=!!python/object:os.system x"])
    with pytest.raises(ConfigError, match="expected key=value"):
        parse_overrides(["=3"])
    assert parse_overrides(["people.count=3", "sensor={noise_std: 0}"]) == {
        "people__count": 3,
        "sensor": {"noise_std": 0},
    }


# --- item 28: streaming and progress --------------------------------------------------------


class _Collect:
    def __init__(self) -> None:
        self.header: Any = None
        self.stamps: list[float] = []

    def begin(self, header: Any) -> None:
        self.header = header

    def add(self, scan: Any, reference: Any, odometry: Any) -> None:
        self.stamps.append(scan.stamp)


def test_streaming_keeps_no_scans_and_gives_the_same_scans() -> None:
    sink = _Collect()
    res = simulate_run("corridor", seed=2, duration=1.0, people__count=3, sink=sink,
                       keep_scans=False)  # fmt: skip
    ref = simulate_run("corridor", seed=2, duration=1.0, people__count=3)
    assert len(res.sequence) == 0 and res.sequence.odometry is None
    assert res.n_kept == len(ref.sequence) == len(sink.stamps) == 11
    np.testing.assert_array_equal(sink.stamps, ref.sequence.stamps)
    assert sink.header.name == ref.sequence.name and sink.header.metadata == ref.sequence.metadata
    mid = ref.sequence[len(ref.sequence) // 2]
    assert res.middle_scan is not None
    np.testing.assert_array_equal(res.middle_scan.ranges, mid.ranges)
    assert res.inf_fraction == pytest.approx(np.isinf(ref.sequence.ranges_matrix()).mean())
    np.testing.assert_array_equal(res.robot_path, ref.robot_path)


@pytest.mark.parametrize("name", ["s.mcap", "sbag"])
def test_streamed_bag_is_identical_to_write_sequence(tmp_path: Path, name: str) -> None:
    from scanguard.io import read_sequence, write_sequence

    (tmp_path / "a").mkdir()
    with BagStreamWriter(check_bag_output(tmp_path / "a" / name)) as bag:
        simulate_run("glass", seed=5, duration=1.0, sink=bag, keep_scans=False)
    seq = simulate("glass", seed=5, duration=1.0)
    write_sequence(seq, tmp_path / "b" / name)
    a, b = tmp_path / "a" / name, tmp_path / "b" / name
    if name.endswith(".mcap"):
        assert a.read_bytes() == b.read_bytes()
    else:
        for f in (f"{name}.mcap", "metadata.yaml"):
            assert (a / f).read_bytes() == (b / f).read_bytes()
    back = read_sequence(a)
    np.testing.assert_array_equal(back.ranges_matrix(), seq.ranges_matrix())
    np.testing.assert_allclose(back.reference, seq.reference, atol=1e-6)
    assert _leftovers(tmp_path / "a") == [name]


def test_cli_streams_and_logs_progress_without_a_terminal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import scanguard.sim.engine as engine

    kept: list[bool] = []
    real = engine.simulate_run

    def spy(*args: Any, **kwargs: Any) -> Any:
        kept.append(kwargs.get("keep_scans", True))
        return real(*args, **kwargs)

    monkeypatch.setattr("scanguard.sim.simulate_run", spy)
    out, png = tmp_path / "c.mcap", tmp_path / "c.png"
    res = _cli("-s", "corridor", "--seed", "3", "-d", "1", "-o", str(out), "--preview", str(png),
               "--set", "people.count=2")  # fmt: skip
    assert res.exit_code == 0, res.output
    assert kept == [False]  # the CLI never keeps the scans in memory
    assert "simulating corridor (seed 3)" in res.stderr and "(100 %)" in res.stderr
    assert "11 at 10.0 Hz, 1440 beams" in res.stdout
    assert out.stat().st_size > 0 and png.read_bytes()[:4] == b"\x89PNG"
    assert _leftovers(tmp_path) == ["c.mcap", "c.png", "c.scenario.yaml"]


# --- items 1, 14, 15, 35: outputs checked before the run, written atomically ----------------


def test_output_with_another_extension_makes_nothing(tmp_path: Path, no_simulation: None) -> None:
    for name in ("out.txt", "out.bag", "out.db3", "out.mcap.tmp"):
        res = _cli("-d", "1", "-o", name, cwd=tmp_path)
        _one_line_error(res, name, "unsupported extension", ".mcap")
    assert _leftovers(tmp_path) == []


def test_output_kinds_are_checked_before_the_run(tmp_path: Path, no_simulation: None) -> None:
    (tmp_path / "dir.mcap").mkdir()
    _one_line_error(_cli("-o", str(tmp_path / "dir.mcap")), "is a directory")
    (tmp_path / "file").write_text("mine")
    _one_line_error(_cli("-o", str(tmp_path / "file")), "is a file")
    _one_line_error(_cli("-o", str(tmp_path / "file" / "x.mcap")), "not a directory")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "notes.txt").write_text("mine")
    _one_line_error(_cli("-o", str(tmp_path / "docs")), "not a ROS 2 bag folder")
    (tmp_path / "a.scenario.yaml").mkdir()
    _one_line_error(_cli("-o", str(tmp_path / "a.mcap")), "a.scenario.yaml", "directory")
    _one_line_error(
        _cli("-o", str(tmp_path / "b.mcap"), "--preview", str(tmp_path / "p.jpg")), ".png"
    )
    (tmp_path / "shot.png").mkdir()
    _one_line_error(_cli("--preview", str(tmp_path / "shot.png")), "is a directory")
    assert (tmp_path / "file").read_text() == "mine"
    assert _leftovers(tmp_path) == ["a.scenario.yaml", "dir.mcap", "docs", "file", "shot.png"]
    assert _leftovers(tmp_path / "docs") == ["notes.txt"]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_special_files_are_never_replaced(tmp_path: Path, no_simulation: None) -> None:
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    _one_line_error(_cli("-o", str(fifo)), "FIFO")
    os.mkfifo(tmp_path / "pipe")
    _one_line_error(_cli("-o", str(tmp_path / "pipe")), "FIFO")
    assert fifo.is_fifo() and (tmp_path / "pipe").is_fifo()
    if Path("/dev/null").exists():
        _one_line_error(_cli("-o", "/dev/null"), "character device")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes anywhere")
def test_unwritable_output_is_refused_before_the_run(tmp_path: Path, no_simulation: None) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        _one_line_error(_cli("-o", str(locked / "a.mcap")), "a.mcap")
        _one_line_error(_cli("--preview", str(locked / "p.png")), "p.png")
    finally:
        locked.chmod(0o755)


def test_symlinked_output_is_followed(tmp_path: Path) -> None:
    target = tmp_path / "real" / "target.mcap"
    target.parent.mkdir()
    link = tmp_path / "link.mcap"
    link.symlink_to(target)
    res = _cli("-d", "0.3", "--set", "people.count=0", "-o", str(link))
    assert res.exit_code == 0, res.output
    assert link.is_symlink() and target.is_file() and target.stat().st_size > 0


def test_existing_bag_folder_is_replaced_whole(tmp_path: Path) -> None:
    for seed in ("1", "2"):
        res = _cli("-d", "0.3", "--seed", seed, "--set", "people.count=0", "-o",
                   str(tmp_path / "bag"))  # fmt: skip
        assert res.exit_code == 0, res.output
    assert _leftovers(tmp_path / "bag") == ["bag.mcap", "metadata.yaml"]
    assert _leftovers(tmp_path) == ["bag", "bag.scenario.yaml"]


def test_disk_space_is_checked_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_simulation: None
) -> None:
    import shutil

    import scanguard.sim.output as output

    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(output.shutil, "disk_usage", lambda p: usage._replace(free=1000))
    _one_line_error(_cli("-d", "10", "-o", str(tmp_path / "a.mcap")), "only", "free")
    assert _leftovers(tmp_path) == []


class _Interrupt:
    """A sink that passes scans on and raises Ctrl-C at the third one."""

    def __init__(self, inner: BagStreamWriter) -> None:
        self.inner = inner

    def begin(self, header: Any) -> None:
        self.inner.begin(header)

    def add(self, scan: Any, reference: Any, odometry: Any) -> None:
        if self.inner.count == 2:
            raise KeyboardInterrupt
        self.inner.add(scan, reference, odometry)


@pytest.mark.parametrize("name", ["a.mcap", "abag"])
def test_interrupted_run_leaves_the_old_output_and_no_temporaries(
    tmp_path: Path, name: str
) -> None:
    dest = tmp_path / "new" / name
    with pytest.raises(KeyboardInterrupt), BagStreamWriter(check_bag_output(dest)) as bag:
        simulate_run("lobby", seed=0, duration=1.0, sink=_Interrupt(bag), keep_scans=False)
    assert _leftovers(tmp_path) == []  # not even the folder made for it
    with BagStreamWriter(check_bag_output(tmp_path / name)) as bag:
        simulate_run("lobby", seed=0, duration=0.2, sink=bag, keep_scans=False)
    before = sorted((p.name, p.read_bytes()) for p in tmp_path.rglob("*") if p.is_file())
    with pytest.raises(KeyboardInterrupt), BagStreamWriter(check_bag_output(tmp_path / name)) as b:
        simulate_run("lobby", seed=1, duration=1.0, sink=_Interrupt(b), keep_scans=False)
    after = sorted((p.name, p.read_bytes()) for p in tmp_path.rglob("*") if p.is_file())
    assert after == before and _leftovers(tmp_path) == [name]


def test_failing_cli_run_writes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(self: BagStreamWriter, *args: Any) -> None:
        raise OutputError(self.path, "cannot write: No space left on device")

    monkeypatch.setattr(BagStreamWriter, "add", fail)
    res = _cli("-d", "0.5", "-o", str(tmp_path / "a.mcap"), "--preview", str(tmp_path / "a.png"))
    _one_line_error(res, "a.mcap", "No space left on device")
    assert _leftovers(tmp_path) == []


def test_killed_simulate_leaves_no_bag_and_the_next_run_cleans_up(tmp_path: Path) -> None:
    code = (
        "import sys; from scanguard.cli import app; "
        "sys.argv = ['scanguard', 'simulate', '-d', '3000', '-o', 'k.mcap']; app()"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            temps = [p for p in tmp_path.iterdir() if p.name.startswith(".k.mcap.")]
            if temps and any(f.stat().st_size > 0 for f in temps[0].rglob("*.mcap")):
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the simulation ended before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert not (tmp_path / "k.mcap").exists()  # no half-written bag at the destination
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".k.mcap.")]
    res = _cli("-d", "0.2", "--set", "people.count=0", "-o", "k.mcap", cwd=tmp_path)
    assert res.exit_code == 0, res.output
    assert _leftovers(tmp_path) == ["k.mcap", "k.scenario.yaml"]


def test_library_errors_are_scanguard_errors() -> None:
    assert issubclass(OutputError, ScanGuardError) and issubclass(ConfigError, ScanGuardError)
    with pytest.raises(OutputError, match="unsupported extension"):
        check_bag_output("x.txt")
    for name in (".", "..", "/"):
        with pytest.raises(OutputError, match="give the bag a name"):
            check_bag_output(name)


def test_bag_named_dot_is_one_line(tmp_path: Path, no_simulation: None) -> None:
    _one_line_error(_cli("-o", ".", cwd=tmp_path))
    assert _leftovers(tmp_path) == []
