"""Command-line interface: parses arguments, calls the library, prints results.

Heavy modules (torch, rosbags, matplotlib) are imported inside the commands so that
``scanguard --help`` stays fast.

Every command runs inside `guarded`, the one error boundary: an expected failure
(`ScanGuardError`, `OSError`, out of memory) becomes one line ``error: <path>: <problem>``
with exit code 1, and Ctrl-C becomes exit code 130; the output layer (`scanguard.fsutil`)
makes sure nothing half-written is left behind either way.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import inspect
import logging
import math
import os
import shlex
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import typer
from rich.console import Console

from scanguard import __version__
from scanguard.errors import ConfigError, ScanGuardError

app = typer.Typer(
    name="scanguard",
    help="Detect faulty 2D LiDAR scan matches with a CNN and keep SLAM honest.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain help: flags look like flags, readable in any width
)
console = Console()
err_console = Console(stderr=True)
logger = logging.getLogger("scanguard.cli")

F = TypeVar("F", bound=Callable[..., Any])

#: Exit code of a run stopped with Ctrl-C (128 + SIGINT), as shells report it.
EXIT_INTERRUPTED = 130

_OS_PROBLEMS = {
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EEXIST: "already exists",
    errno.EISDIR: "is a directory",
    errno.ENOTDIR: "not a directory",
    errno.EROFS: "read-only file system",
    errno.ENOENT: "no such file or directory",
    errno.ENAMETOOLONG: "file name too long",
    errno.ENOTEMPTY: "directory not empty",
    errno.EMFILE: "too many open files",
    errno.EIO: "input/output error",
}


def _printable(text: str, limit: int = 1000) -> str:
    """``text`` on one line: control characters escaped, at most ``limit`` characters."""
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return out if len(out) <= limit else out[: limit - 1] + "…"


def os_error_text(exc: OSError) -> str:
    """``<path>: <problem>`` for an `OSError` (``<problem>`` alone when it names no path)."""
    problem = _OS_PROBLEMS.get(exc.errno or -1) or exc.strerror or str(exc) or type(exc).__name__
    if exc.filename is None:
        return problem
    where = os.fsdecode(exc.filename) if isinstance(exc.filename, bytes) else str(exc.filename)
    if exc.filename2 is not None:
        where = f"{where} -> {exc.filename2}"
    return f"{where}: {problem}"


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a `KeyboardInterrupt` is in ``exc``'s chain (numba's ``SystemError`` wraps it)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _fail(message: str) -> NoReturn:
    from rich.markup import escape

    err_console.print(
        f"[bold red]error:[/bold red] {escape(_printable(message))}",
        highlight=False,
        soft_wrap=True,
    )
    raise typer.Exit(1)


class _Signals:
    """SIGINT/SIGTERM during a command: remembered, and raised where that is safe.

    The signal raises `KeyboardInterrupt` as Python's default does, except inside an LLVM
    callback (numba compiling a kernel), where an exception is swallowed or crashes the
    process: there the signal is re-sent a moment later. ``received`` stays set, so an
    error that a swallowed interrupt turns into (numba: ``no compiled object yet``) still
    ends as an interruption.
    """

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, Any] = {}
        self._active = False

    def __enter__(self) -> _Signals:
        import signal
        import threading

        self.received = None
        self._active = True
        if threading.current_thread() is not threading.main_thread():
            return self
        for sig, default in (
            (signal.SIGINT, signal.default_int_handler),
            (signal.SIGTERM, signal.SIG_DFL),
        ):
            if signal.getsignal(sig) is default:  # never replace someone else's handler
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        import signal

        self._active = False
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _resend(self, signum: int) -> None:
        if self._active:  # the command may have ended meanwhile
            os.kill(os.getpid(), signum)

    def _handle(self, signum: int, frame: Any) -> None:
        import threading

        self.received = signum
        f = frame
        while f is not None:
            if "llvmlite" in f.f_code.co_filename:
                retry = threading.Timer(0.05, self._resend, (signum,))
                retry.daemon = True
                retry.start()
                return
            f = f.f_back
        raise KeyboardInterrupt

    def exit_code(self) -> int:
        """130 for Ctrl-C (SIGINT), 143 for SIGTERM."""
        return 128 + (self.received or 2)


def _interrupted(signals: _Signals | None = None) -> NoReturn:
    code = EXIT_INTERRUPTED if signals is None else signals.exit_code()
    what = "terminated" if code == 143 else "interrupted"
    err_console.print(
        f"[yellow]{what}[/yellow]: stopped, no partial output was kept", highlight=False
    )
    raise typer.Exit(code)


def guarded(fn: F) -> F:
    """The CLI's error boundary: one line on stderr and exit 1 for expected errors.

    `ScanGuardError`, `OSError` (permission, no space, exists, is a directory, ...) and
    `MemoryError` become ``error: <path>: <problem>`` with exit code 1; Ctrl-C (also when
    numba wraps it in a ``SystemError`` or swallows it while compiling) becomes exit code 130
    and SIGTERM 143, after the output layer has removed its temporaries. Anything else is a
    bug and keeps its traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        signals = _Signals()
        try:
            with signals:
                return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, typer.TyperException):
            raise
        except KeyboardInterrupt:
            _interrupted(signals)
        except ScanGuardError as exc:
            if signals.received or _caused_by_interrupt(exc):
                _interrupted(signals)
            logger.debug("%s", type(exc).__name__, exc_info=True)
            _fail(str(exc))
        except OSError as exc:
            if signals.received or _caused_by_interrupt(exc):
                _interrupted(signals)
            logger.debug("%s", type(exc).__name__, exc_info=True)
            _fail(os_error_text(exc))
        except MemoryError as exc:
            detail = f" ({exc})" if str(exc) else ""
            _fail(f"out of memory{detail}: use a smaller input or smaller settings")
        except Exception as exc:
            if signals.received or _caused_by_interrupt(exc):
                _interrupted(signals)
            raise

    return wrapper  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class Bound:
    """Accepted values of a numeric option: finite, and ``low <= v`` (``low < v`` if open)."""

    low: float | None = None
    open_low: bool = False
    high: float | None = None

    def problem(self, value: float) -> str | None:
        """Why ``value`` is not accepted (None: accepted)."""
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be a finite number, got {value}"
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return f"must be {'>' if self.open_low else '>='} {self.low:g}, got {value}"
        if self.high is not None and value > self.high:
            return f"must be <= {self.high:g}, got {value}"
        return None


NON_NEGATIVE = Bound(low=0)
POSITIVE = Bound(low=0, open_low=True)
AT_LEAST_ONE = Bound(low=1)


def _option_name(param: inspect.Parameter) -> str:
    decls = getattr(param.default, "param_decls", None) or ()
    longs = [d for d in decls if isinstance(d, str) and d.startswith("--")]
    if longs:
        return longs[0].split("/")[0]
    if type(param.default).__name__ == "ArgumentInfo":
        return param.name.upper()
    return "--" + param.name.replace("_", "-")


def checked(**bounds: Bound) -> Callable[[F], F]:
    """Check numeric options against `Bound`s before the command runs (one-line errors).

    Example:
        >>> @app.command()  # doctest: +SKIP
        ... @guarded
        ... @checked(seed=NON_NEGATIVE, duration=POSITIVE)
        ... def simulate(seed: int = ..., duration: float = ...) -> None: ...
    """

    def deco(fn: F) -> F:
        sig = inspect.signature(fn)
        names = {name: _option_name(sig.parameters[name]) for name in bounds}

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            given = sig.bind_partial(*args, **kwargs).arguments
            for name, bound in bounds.items():
                value = given.get(name)
                for v in value if isinstance(value, (list, tuple)) else [value]:
                    problem = None if v is None else bound.problem(v)
                    if problem is not None:
                        raise ConfigError(f"{names[name]} {problem}")
            return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return deco


def outputs(**checks: Callable[[str], object]) -> Callable[[F], F]:
    """Check output options (``name=check(value)``) before the command does any work.

    Example:
        >>> @outputs(preview=png_output)  # doctest: +SKIP
    """

    def deco(fn: F) -> F:
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            given = sig.bind_partial(*args, **kwargs).arguments
            for name, check in checks.items():
                if given.get(name) is not None:
                    check(str(given[name]))
            return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return deco


def bag_output(path: str) -> object:
    """A bag destination: one ``*.mcap`` file, or a bag folder (a name without extension)."""
    from scanguard.fsutil import check_output_path

    if path.lower().endswith(".mcap"):
        return check_output_path(path, "file", suffixes=(".mcap",))
    return check_output_path(path, "dir", suffixes=(".mcap", ""))


def png_output(path: str) -> object:
    """A ``*.png`` file destination."""
    from scanguard.fsutil import check_output_path

    return check_output_path(path, "file", suffixes=(".png",))


def _command_record(ctx: typer.Context) -> dict[str, Any]:
    """The resolved command line of ``ctx`` (defaults included), for a result's marker."""
    params = dict(ctx.params)
    words = ["scanguard", *ctx.command_path.split()[1:]]
    for p in ctx.command.params:
        if p.name not in params:
            continue
        value = params[p.name]
        values = list(value) if isinstance(value, (list, tuple)) else [value]
        if p.param_type_name == "argument":
            words += [str(v) for v in values]
            continue
        flag = max((o for o in p.opts if o.startswith("--")), key=len, default=p.opts[0])
        if getattr(p, "is_flag", False):
            if value:
                words.append(flag)
            continue
        for v in values:
            if v is not None:
                words += [flag, str(v)]
    return {
        "name": ctx.command_path.split(maxsplit=1)[-1],
        "command": shlex.join(words),
        "options": params,
        "cwd": os.getcwd(),
    }


def _result_dir(ctx: typer.Context, out: str, overwrite: bool) -> Any:
    """A `ResultDir` for ``--out``, checked now (before any long work)."""
    from scanguard.fsutil import ResultDir

    return ResultDir(out, overwrite=overwrite, record=_command_record(ctx))


_OVERWRITE_HELP = (
    "Write into an existing folder that scanguard did not create (only files of the same "
    "names are replaced; other files are kept)."
)


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"scanguard {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version."
    ),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
) -> None:
    """Detect faulty 2D LiDAR scan matches (global options)."""
    from scanguard.logging_utils import configure_logging

    configure_logging(verbose)


# --- commands: info (io) ---------------------------------------------------------------------


@app.command()
@guarded
def info(
    path: str = typer.Argument(..., help="Bag (.bag, .mcap, .db3, ROS 2 folder) or CARMEN log."),
    scan_topic: str | None = typer.Option(
        None, "--scan-topic", help="LaserScan topic (CARMEN: FLASER, RLASER, ROBOTLASER1)."
    ),
    odom_topic: str | None = typer.Option(
        None, "--odom-topic", help="Odometry topic (CARMEN: ODOM or laser)."
    ),
    reference_topic: str | None = typer.Option(
        None, "--reference-topic", help="Reference pose topic (Odometry or PoseStamped)."
    ),
    reference: str | None = typer.Option(
        None, "--reference", help="TUM trajectory file, or 'static' (sensor never moved)."
    ),
    format: str | None = typer.Option(
        None, "--format", help="Reader (rosbag, carmen) when the extension does not say."
    ),
    lenient: bool = typer.Option(
        False, "--lenient", help="Skip malformed lines/messages (counted) instead of refusing."
    ),
    corrected: bool | None = typer.Option(
        None,
        "--corrected/--not-corrected",
        help="CARMEN: the log's poses are SLAM-corrected (reference), or raw odometry. "
        "(default: from the file name or its NEFF lines)",
    ),
) -> None:
    """Summarise a recording: scans, beams, field of view, rate, odometry, reference, topics."""
    from rich.markup import escape
    from rich.table import Table

    from scanguard.io import read_sequence, summarize

    seq = read_sequence(
        path,
        format=format,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
        reference=reference,
        reader_options=None if corrected is None else {"corrected": corrected},
        lenient=lenient,
    )
    s = summarize(seq)
    unknown = "unknown (see note)" if s["stamps_note"] else "unknown"
    table = Table(title=escape(_printable(path)), show_header=False, title_justify="left")
    table.add_column("what", style="bold", no_wrap=True)
    table.add_column("value", overflow="fold")
    table.add_row("format", f"{s['format']} (sensor: {s['sensor']})")
    table.add_row("scans", str(s["scans"]))
    table.add_row("beams", " / ".join(str(b) for b in s["beams"]))
    table.add_row("field of view", f"{s['fov_deg']:.1f} deg")
    table.add_row("range limits", f"{s['range_min']:.2f} .. {s['range_max']:.2f} m")
    table.add_row("rate", unknown if s["rate_hz"] is None else f"{s['rate_hz']:.2f} Hz")
    table.add_row("duration", unknown if s["duration_s"] is None else f"{s['duration_s']:.1f} s")
    table.add_row("invalid beams", f"{100 * s['invalid_fraction']:.1f} %")
    odo = f"yes ({s['odometry_source']})" if s["odometry"] else "no"
    if s.get("odometry_note"):
        odo = f"{odo}; {s['odometry_note']}"
    table.add_row("odometry", escape(_printable(odo)))
    ref = f"yes ({s['reference_kind']}: {s['reference_source']})" if s["reference"] else "no"
    table.add_row("reference", ref)
    off = s["laser_offset"]
    table.add_row("laser offset", f"x {off[0]:.3f} m, y {off[1]:.3f} m, yaw {off[2]:.3f} rad")
    topics = "\n".join(
        f"{escape(_printable(name))}  [dim]{escape(_printable(str(t['type'])))}[/dim]  {t['count']}"
        for name, t in sorted(s["topics"].items())
    )
    table.add_row("topics found", topics or "-")
    if s.get("other_lines"):
        other = ", ".join(f"{k} ({v})" for k, v in s["other_lines"].items())
        table.add_row("other lines", escape(_printable(other)))
    if s.get("stamps_steps_back"):
        table.add_row("stamps", f"{s['stamps_steps_back']} steps back in file order (kept)")
    if s.get("skipped"):
        table.add_row("skipped (--lenient)", str(s["skipped"]))
    if s["stamps_note"]:
        table.add_row("note", f"[yellow]{escape(_printable(s['stamps_note']))}[/yellow]")
    console.print(table)


# --- commands: simulate (sim) ----------------------------------------------------------------


@app.command()
@guarded
@checked(
    seed=NON_NEGATIVE,
    duration=POSITIVE,
    stride=AT_LEAST_ONE,
    scan_rate=POSITIVE,
    people=NON_NEGATIVE,
)
@outputs(output=bag_output, preview=png_output)  # before the simulation, not after it
def simulate(
    scenario: str = typer.Option(
        "lobby", "--scenario", "-s", help="lobby, corridor, glass, hall, office, or a YAML file."
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of all randomness (layout, people, noise)."),
    duration: float = typer.Option(60.0, "--duration", "-d", help="Simulated seconds."),
    output: str | None = typer.Option(
        None, "--output", "-o", help="ROS 2 bag to write (*.mcap = one MCAP file)."
    ),
    preview: str | None = typer.Option(
        None, "--preview", help="PNG with the world, robot path and people tracks."
    ),
    stride: int | None = typer.Option(None, "--stride", help="Keep every k-th scan."),
    scan_rate: float | None = typer.Option(None, "--scan-rate", help="Scan rate (Hz)."),
    people: int | None = typer.Option(None, "--people", help="Number of pedestrians."),
    sensor: str | None = typer.Option(
        None, "--sensor", help="rplidar_a3, sick_lms, hokuyo_utm30lx or pr2_base."
    ),
    set_: list[str] = typer.Option(  # noqa: B008 - typer declares options this way
        [], "--set", help="Override any config value: --set people.carts=3 (repeatable)."
    ),
) -> None:
    """Simulate a crowded LiDAR recording with exact ground truth and write it as a ROS 2 bag.

    The bag is streamed to disk while the simulation runs (constant memory) under a temporary
    name and renamed into place at the end. The scenario, the run's size and every output are
    checked before the simulation starts.
    """
    import contextlib
    from pathlib import Path

    import numpy as np
    from rich.markup import escape
    from rich.table import Table

    from scanguard.config import save_config
    from scanguard.errors import ConfigError
    from scanguard.fsutil import check_output_path
    from scanguard.sim import parse_overrides, plan_simulation, simulate_run
    from scanguard.sim.limits import check_seed
    from scanguard.sim.output import (
        BagStreamWriter,
        check_bag_output,
        check_free_space,
        check_preview_output,
    )

    if output is None and preview is None:
        raise ConfigError("nothing to do: give --output (bag) and/or --preview (PNG)")
    check_seed(seed)
    overrides = parse_overrides(set_)
    for key, val in {
        "stride": stride,
        "scan_rate_hz": scan_rate,
        "people__count": people,
        "sensor__model": sensor,
    }.items():
        if val is not None:
            overrides[key] = val
    # everything that can be refused is refused before the simulation starts
    cfg, seconds, plan = plan_simulation(scenario, duration=duration, keep_scans=False, **overrides)
    bag = cfg_dest = png = None
    if output is not None:
        bag = check_bag_output(output)
        given = Path(output)
        cfg_dest = check_output_path(given.parent / f"{given.stem}.scenario.yaml", "file")
        check_free_space(bag, plan.bag_bytes)
    if preview is not None:
        png = check_preview_output(preview)
    with contextlib.ExitStack() as stack:
        writer = None if bag is None else stack.enter_context(BagStreamWriter(bag))
        res = simulate_run(
            cfg, seed=seed, duration=seconds, progress=True, sink=writer, keep_scans=False
        )
    written = []
    if bag is not None and cfg_dest is not None:
        save_config(res.config, cfg_dest.parent, name=cfg_dest.name)
        written += [str(output), str(Path(str(output)).with_name(cfg_dest.name))]
    if png is not None:
        from scanguard.sim.preview import save_preview

        save_preview(res, png)
        written.append(str(preview))
    sensor_info = res.sequence.sensor
    assert sensor_info is not None  # simulate_run always sets it
    steps = np.diff(res.robot_path[:: res.config.stride, :2], axis=0)
    table = Table(title=f"simulated {res.config.name} (seed {seed})", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row(
        "scans",
        f"{res.n_kept} at {sensor_info.rate_hz or 0:.1f} Hz, {sensor_info.n_beams} beams",
    )
    table.add_row("sensor", f"{sensor_info.name}, {sensor_info.fov_deg:.0f} deg")
    table.add_row("agents", str(res.sequence.metadata["n_people"]))
    table.add_row("robot path", f"{np.hypot(steps[:, 0], steps[:, 1]).sum():.1f} m")
    table.add_row("inf beams", f"{100 * res.inf_fraction:.1f} %")
    table.add_row("written", escape("\n".join(written)))
    console.print(table)


# --- commands: dataset (dataset) -------------------------------------------------------------

dataset_app = typer.Typer(
    help="Build, inspect and export labelled scan-pair datasets.", no_args_is_help=True
)
app.add_typer(dataset_app, name="dataset")


@dataset_app.command("build")
@guarded
@checked(max_scans=Bound(low=2), workers=AT_LEAST_ONE)
def dataset_build(
    out: str = typer.Option(..., "--out", "-o", help="Build directory (resumable)."),
    config: str | None = typer.Option(
        None, "--config", "-c", help="Dataset YAML (e.g. configs/paper.yaml)."
    ),
    recording: list[str] = typer.Option(  # noqa: B008
        [], "--recording", "-r", help="Label a recording instead of simulating (repeatable)."
    ),
    reference: str | None = typer.Option(
        None, "--reference", help="Reference for --recording: a TUM file or 'static'."
    ),
    matcher: str | None = typer.Option(None, "--matcher", help="Override the config's matcher."),
    initial: str | None = typer.Option(
        None, "--initial", help="Recordings: identity|odometry|simulated_odometry|auto."
    ),
    max_scans: int | None = typer.Option(None, "--max-scans", help="Recordings: first N scans."),
    workers: int | None = typer.Option(
        None, "--workers", "-j", help="Parallel sequence builds. (default: 1; Ray: all CPUs)"
    ),
    executor: str = typer.Option("local", "--executor", help="Where tasks run: local or ray."),
    address: str | None = typer.Option(
        None, "--address", help="Ray cluster address (--executor ray; default: a local Ray)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Rebuild files of another config."),
    scan_topic: str | None = typer.Option(
        None, "--scan-topic", help="Recordings: LaserScan topic (CARMEN: FLASER, RLASER, ...)."
    ),
    odom_topic: str | None = typer.Option(None, "--odom-topic", help="Recordings: odometry topic."),
    reference_topic: str | None = typer.Option(
        None, "--reference-topic", help="Recordings: reference pose topic."
    ),
) -> None:
    """Simulate + match + label (with --config), or label recordings (with --recording).

    One task per sequence or recording, each writing its own shard; a rerun resumes. A
    recording that fails is reported, the others finish, and the exit code is then 1.
    """
    import time

    from rich.markup import escape

    from scanguard.dataset import DatasetConfig, build_dataset
    from scanguard.dataset import build as build_mod
    from scanguard.fsutil import check_output_path
    from scanguard.runtime.executor import make_executor

    # all recordings in one call: registered as pending together, counted together
    builder: Callable[..., Any] = build_mod.build_from_recordings

    check_output_path(out, "dir")  # before any work: a file, a device, unwritable
    topics = {
        k: v
        for k, v in (
            ("scan_topic", scan_topic),
            ("odom_topic", odom_topic),
            ("reference_topic", reference_topic),
        )
        if v is not None
    }
    if topics and not recording:
        raise ConfigError("--scan-topic/--odom-topic/--reference-topic apply to --recording only")
    if topics and not set(topics) <= set(inspect.signature(builder).parameters):
        raise ConfigError(
            "this version of dataset build cannot choose topics; use `scanguard info` to find "
            "them, or a recording with one LaserScan topic"
        )
    cfg = DatasetConfig.from_yaml(config) if config else DatasetConfig()
    if matcher:
        cfg = cfg.model_copy(update={"matcher": matcher})
        cfg = DatasetConfig.from_dict(cfg.model_dump(), source="--matcher")
    valid_initial = ("identity", "odometry", "simulated_odometry", "auto")
    if initial is not None and initial not in valid_initial:
        raise ConfigError(f"--initial must be one of {', '.join(valid_initial)}, got {initial!r}")
    _choice("--executor", executor, ("local", "ray"))
    pool = make_executor(executor, address=address, workers=workers)
    t0 = time.perf_counter()
    if recording:
        if "executor" in inspect.signature(builder).parameters:
            topics["executor"] = pool  # failures reported, the others finish
        summary = builder(
            list(recording),
            out,
            cfg,
            reference=reference,
            initial_guess=initial,
            max_scans=max_scans,
            overwrite=overwrite,
            **topics,
        )
    else:
        if not config:
            raise ConfigError("give --config (simulated build) or --recording PATH")
        # local: one worker builds in this process (progress per pair), more in a pool
        summary = build_dataset(
            cfg,
            out,
            overwrite=overwrite,
            workers=workers or 1,
            executor=pool if executor == "ray" else None,
        )
    n_built, n_resumed = len(summary.built), len(summary.skipped)
    cols = ("sequence", "environment", "split", "pairs", "normal", "fault", "ambiguous")
    table = _table(
        f"{out}: {n_built} built, {n_resumed} resumed",
        [(c, c in ("pairs", "normal", "fault", "ambiguous")) for c in cols],
    )
    for e in summary.entries:
        table.add_row(
            e["sequence"],
            e["environment"],
            e["split"],
            *(str(e[k]) for k in ("pairs", "normal", "fault", "ambiguous")),
        )
    tot = summary.totals()
    table.add_row("all", "", "", *(str(tot[k]) for k in ("pairs", "normal", "fault", "ambiguous")))
    console.print(table)
    console.print(f"done in {time.perf_counter() - t0:.1f} s")
    failed = getattr(summary, "failed", {})
    for what, error in failed.items():
        console.print(f"failed   {escape(what)}: {escape(error)}", highlight=False, soft_wrap=True)
    if failed:
        _fail(f"{len(failed)} failed (a rerun of the same command retries what can succeed)")


@dataset_app.command("stats")
@guarded
def dataset_stats(
    store: list[str] = typer.Argument(..., help="Dataset directories and/or pair files."),  # noqa: B008
    out: str | None = typer.Option(
        None, "--out", "-o", help="Histogram/JSON directory (default: <first store>/stats)."
    ),
) -> None:
    """Per-environment normal/fault/ambiguous counts and error histograms (PNG)."""
    from scanguard.dataset import PairStore, write_stats
    from scanguard.fsutil import check_output_path

    first = Path(store[0])
    dest = Path(out) if out else (first if first.is_dir() else first.parent) / "stats"
    if out:
        check_output_path(dest, "dir")
    ps = PairStore.open(store)
    if not out:
        check_output_path(dest, "dir")
    rows, js = write_stats(ps, dest)
    cols = ("environment", "splits", "sequences", "pairs", "normal", "fault", "ambiguous")
    table = _table(
        f"{len(ps)} pairs",
        [(c, c not in ("environment", "splits")) for c in (*cols, "fault rate")],
    )
    for r in rows:
        table.add_row(
            r["environment"],
            ",".join(r["splits"]),
            *(str(r[k]) for k in cols[2:]),
            f"{r['fault_rate']:.1%}",
        )
    console.print(table)
    console.print(f"histograms and {js.name} in {dest}")


@dataset_app.command("export-png")
@guarded
@checked(per_class=AT_LEAST_ONE, size=AT_LEAST_ONE, seed=NON_NEGATIVE)
def dataset_export_png(
    ctx: typer.Context,
    store: list[str] = typer.Argument(..., help="Dataset directories and/or pair files."),  # noqa: B008
    out: str = typer.Option(..., "--out", "-o", help="Root of <env>/<class>/*.png."),
    per_class: int | None = typer.Option(
        None, "--per-class", "-n", help="At most N images per environment and class."
    ),
    kind: str = typer.Option("paper", "--style", help="paper | occupancy | metric."),
    size: int = typer.Option(256, "--size", help="Image side (px)."),
    ambiguous: bool = typer.Option(False, "--ambiguous", help="Also export ambiguous pairs."),
    seed: int = typer.Option(0, "--seed", help="Seed of the per-class subsample."),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
) -> None:
    """Write pair images in the paper's folder layout (<env>/normal, <env>/fault)."""
    from scanguard.dataset import PairStore
    from scanguard.detect.images import export_png
    from scanguard.detect.render import RenderStyle

    result = _result_dir(ctx, out, overwrite)
    style = RenderStyle.from_dict({"kind": kind, "size": size}, source="--style/--size")
    ps = PairStore.open(store)
    with result as tmp:
        written = export_png(
            ps,
            tmp,
            style,
            per_class=per_class,
            include_ambiguous=ambiguous,
            seed=seed,
            progress=True,
        )
    console.print(f"images in {out}", highlight=False)
    for env, counts in written.items():
        console.print(f"{env}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))


@dataset_app.command("merge")
@guarded
def dataset_merge(
    sources: list[str] = typer.Argument(..., help="Dataset directories and/or pair files."),  # noqa: B008
    out: str = typer.Option(..., "--out", "-o", help="Merged dataset directory."),
) -> None:
    """Copy several builds into one dataset directory with one manifest."""
    from scanguard.dataset import PairStore, merge_stores
    from scanguard.fsutil import check_output_path

    check_output_path(out, "dir")
    dest = merge_stores(sources, out)
    console.print(f"{dest}: {len(PairStore.open(dest))} pairs")


# --- commands: train / evaluate / export (model) ---------------------------------------------


@app.command()
@guarded
@checked(epochs=AT_LEAST_ONE, max_train=AT_LEAST_ONE, seed=NON_NEGATIVE, threads=AT_LEAST_ONE)
def train(
    ctx: typer.Context,
    data: list[str] = typer.Option(  # noqa: B008
        ..., "--data", "-d", help="Pair store(s): dataset folder(s) and/or .h5 files."
    ),
    out: str = typer.Option(..., "--out", "-o", help="Output folder (model.pt, curves.png, ...)."),
    config: str | None = typer.Option(None, "--config", "-c", help="Training YAML."),
    preset: str | None = typer.Option(
        None,
        "--preset",
        help="paper|compact|multiscale|cnn+metrics|cnn+metrics+odometry|compact128|tiny.",
    ),
    epochs: int | None = typer.Option(None, "--epochs", help="Override the epoch count."),
    max_train: int | None = typer.Option(None, "--max-train", help="Seeded training subset."),
    seed: int | None = typer.Option(None, "--seed", help="Override the seed."),
    threads: int | None = typer.Option(None, "--threads", help="Torch threads."),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
) -> None:
    """Train the fault-detection CNN (best epoch on the validation split).

    Under torchrun (torchrun --nproc-per-node N --no-python scanguard train ...) the processes
    train one model with DistributedDataParallel (gloo on CPU, nccl with CUDA) on the same
    global batch; rank 0 writes the output.
    """
    # idle OpenMP workers must sleep, not spin: the machine is shared with other jobs
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from rich.markup import escape

    from scanguard.detect.train import TrainConfig, init_distributed
    from scanguard.detect.train import train as run_training

    cfg = TrainConfig.from_yaml(config) if config else TrainConfig()
    updates: dict[str, Any] = {}
    if preset is not None:
        updates.update(preset=preset, model=None, style=None)
    for key, val in (("epochs", epochs), ("max_train", max_train), ("seed", seed)):
        if val is not None:
            updates[key] = val
    if threads is not None:
        updates["threads"] = threads
    if updates:
        cfg = TrainConfig.from_dict({**cfg.model_dump(), **updates}, source="command line")
    rank, _world = init_distributed()  # under torchrun: DDP, rank 0 writes
    if rank != 0:
        run_training(cfg, data if len(data) > 1 else data[0], out)
        return
    result = _result_dir(ctx, out, overwrite)
    with result as tmp:
        res = run_training(cfg, data if len(data) > 1 else data[0], tmp)
    t = _table(
        f"training {res.checkpoint['model_config']['preset']}",
        [(c, True) for c in ("epoch", "train loss", "train acc", "val loss", "val acc", "img/s")],
    )
    best = res.checkpoint["info"]["best_epoch"]
    for h in res.history:
        mark = " *" if h["epoch"] == best else ""
        t.add_row(
            f"{h['epoch']}{mark}",
            f"{h['train_loss']:.4f}",
            f"{h['train_accuracy']:.4f}",
            f"{h['val_loss']:.4f}",
            f"{h['val_accuracy']:.4f}",
            f"{h['images_per_s']:.0f}",
        )
    console.print(t)
    console.print(
        f"best epoch {best}, threshold {res.checkpoint['threshold']:.3f}; "
        f"model in [bold]{escape(str(Path(out) / 'model.pt'))}[/bold] (curves.png, "
        "history.json, config.yaml)"
    )


def _fmt(v: Any, pct: bool = False) -> str:
    import math

    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, float):
        return f"{100 * v:.1f}%" if pct else f"{v:.3f}"
    return str(v)


@app.command()
@guarded
def evaluate(
    ctx: typer.Context,
    data: list[str] = typer.Option(  # noqa: B008
        ..., "--data", "-d", help="Pair store(s) to evaluate on."
    ),
    model: str | None = typer.Option(None, "--model", "-m", help="model.pt (default: shipped)."),
    out: str | None = typer.Option(None, "--out", "-o", help="Results folder (JSON, CSV, PNG)."),
    split: list[str] = typer.Option(  # noqa: B008
        ["test", "heldout"], "--split", "-s", help="Split(s) to evaluate; 'all' = every pair."
    ),
    environment: list[str] = typer.Option(  # noqa: B008
        [], "--environment", "-e", help="Only these environments (repeatable)."
    ),
    baselines: str = typer.Option(
        "all", "--baselines", help="'all', 'none' or a comma list (residual,overlap,...)."
    ),
    baseline_data: list[str] = typer.Option(  # noqa: B008
        [], "--baseline-data", help="Store whose train split fits the baselines (default: --data)."
    ),
    backend: str = typer.Option("torch", "--backend", help="torch or onnx."),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    per_store: bool = typer.Option(
        False,
        "--per-store",
        help="Evaluate each --data store on its own (one task each) into OUT/<name>/, "
        "plus one merged OUT/results.csv; resumable.",
    ),
    executor: str = typer.Option(
        "local", "--executor", help="--per-store: where tasks run, local or ray."
    ),
    address: str | None = typer.Option(
        None, "--address", help="Ray cluster address (--executor ray; default: a local Ray)."
    ),
    workers: int | None = typer.Option(
        None, "--workers", "-j", help="--per-store: parallel stores. (default: 1; Ray: all CPUs)"
    ),
) -> None:
    """Paper Table 2 per environment (fault = positive) + baselines; ROC/confusion PNGs."""
    from rich.markup import escape

    from scanguard.detect.evaluate import evaluate_store

    names: list[str] | None
    if baselines == "all":
        names = None
    elif baselines == "none":
        names = []
    else:
        names = [b.strip() for b in baselines.split(",") if b.strip()]
    if per_store:
        _evaluate_per_store(
            ctx,
            data,
            out,
            executor=executor,
            address=address,
            workers=workers,
            model=model,
            splits=None if "all" in split else split,
            environments=environment or None,
            baselines=names,
            baseline_store=(baseline_data if len(baseline_data) > 1 else baseline_data[0])
            if baseline_data
            else None,
            backend=backend,
        )
        return
    if executor != "local" or address is not None or workers is not None:
        raise ConfigError("--executor, --address and --workers apply to --per-store only")
    result = _result_dir(ctx, out, overwrite) if out else None
    with result if result is not None else contextlib.nullcontext() as tmp:
        try:
            res = evaluate_store(
                model,
                data if len(data) > 1 else data[0],
                tmp,
                splits=None if "all" in split else split,
                environments=environment or None,
                baselines=names,
                baseline_store=(baseline_data if len(baseline_data) > 1 else baseline_data[0])
                if baseline_data
                else None,
                backend=backend,
            )
        except ScanGuardError as exc:
            text = str(exc)
            if (
                "no labelled pairs" in text
                and "train" in text
                and names != []
                and not baseline_data
                and "--baseline" not in text
            ):
                raise ConfigError(
                    f"{text}; the baselines are fitted on a train split: give "
                    "--baseline-data STORE (e.g. a simulated build) or --baselines none"
                ) from exc
            raise
    counts = _table(
        "fault detection (positive class: fault): counts",
        [
            ("method", False),
            ("environment", False),
            *((k, True) for k in ("TP", "FN", "FP", "TN")),
            ("ambiguous (flagged)", True),
        ],
    )
    scores = _table(
        "fault detection (positive class: fault): scores",
        [
            ("method", False),
            ("environment", False),
            *(
                (k, True)
                for k in (
                    "recall",
                    "precision",
                    "accuracy",
                    "bal. acc.",
                    "F1",
                    "ECE",
                    "AUC",
                    "threshold",
                )
            ),
        ],
    )
    last = None
    for r in res.rows:
        if last is not None and r["method"] != last:
            counts.add_section()
            scores.add_section()
        last = r["method"]
        counts.add_row(
            r["method"],
            r["environment"],
            *(str(r[k]) for k in ("TP", "FN", "FP", "TN")),
            f"{r['n_ambiguous']} ({_fmt(r['ambiguous_flagged'], pct=True)})",
        )
        scores.add_row(
            r["method"],
            r["environment"],
            *(_fmt(r[k], pct=True) for k in ("recall", "precision", "accuracy")),
            _fmt(r.get("balanced_accuracy")),
            _fmt(r["f1"], pct=True),
            _fmt(r.get("ece")),
            _fmt(r["auc"]),
            _fmt(r["threshold"]),
        )
    console.print(counts)
    console.print()
    console.print(scores)
    if out:
        console.print(
            f"results in [bold]{escape(out)}[/bold] (results.json, results.csv, roc.png, "
            "reliability.png, ...)"
        )


def _evaluate_per_store(
    ctx: typer.Context,
    data: list[str],
    out: str | None,
    *,
    executor: str,
    address: str | None,
    workers: int | None,
    **options: Any,
) -> None:
    """``evaluate --per-store``: one task per store, merged table (`scale.evaluate_many`)."""
    from rich.markup import escape

    from scanguard.apps.evaluate_many import evaluate_many
    from scanguard.runtime.executor import make_executor

    if not out:
        raise ConfigError("--per-store needs --out (a folder per store plus the merged table)")
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    _choice("--executor", executor, ("local", "ray"))
    pool = make_executor(executor, address=address, workers=workers)
    record = _command_record(ctx)

    def show(res: Any) -> None:
        tail = f": {res.error}" if res.error else ""
        console.print(
            f"{res.status:8s} {escape(str(res.store))}{escape(tail)}",
            highlight=False,
            soft_wrap=True,
        )

    results = evaluate_many(
        data,
        out,
        pool,
        record={"command": record["command"], "cwd": record["cwd"]},
        on_result=show,
        **options,
    )
    console.print(
        f"table in [bold]{escape(str(Path(out) / 'results.md'))}[/bold] (and results.csv)",
        highlight=False,
    )
    failed = sum(r.status == "failed" for r in results)
    if failed:
        _fail(f"{failed} of {len(results)} stores failed (see {Path(out) / 'results.md'})")


_CALIBRATION_METHODS = ("temperature", "platt")


def _calibration_markdown(report: dict[str, Any]) -> str:
    """The calibration report as Markdown (parameters, metrics before and after)."""
    cal = report["calibration"]
    params = (
        f"temperature T = {cal['temperature']:.4f} (p = sigmoid(z / T))"
        if cal["method"] == "temperature"
        else f"Platt a = {cal['a']:.4f}, b = {cal['b']:.4f} (p = sigmoid(a z + b))"
    )
    pairs = report["pairs"]
    lines = [
        "# Calibration",
        "",
        f"* model: `{report['model']}`",
        f"* fitted on: {cal['fitted_on']}",
        f"* pairs: {pairs['normal']} normal, {pairs['fault']} fault, "
        f"{pairs['ambiguous']} ambiguous (excluded)",
        f"* method: {cal['method']}; {params}",
        f"* threshold rule: maximise balanced accuracy, ties -> closest to 0.5: "
        f"**{cal['threshold']:.4f}**",
        "",
        "| | threshold | accuracy | balanced accuracy | recall | precision | F1 | ECE |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key in ("before", "after"):
        m = report[key]
        lines.append(
            f"| {key} | "
            + " | ".join(
                _fmt(m[k])
                for k in (
                    "threshold",
                    "accuracy",
                    "balanced_accuracy",
                    "recall",
                    "precision",
                    "f1",
                    "ece",
                )
            )
            + " |"
        )
    lines += [
        "",
        "Reliability diagrams: `reliability_before.png`, `reliability_after.png` (15 "
        "equal-width bins of the fault probability).",
        "",
    ]
    return "\n".join(lines)


@app.command()
@guarded
@checked(max_scans=Bound(low=2))
def calibrate(
    ctx: typer.Context,
    out: str = typer.Option(
        ..., "--out", "-o", help="Output folder (model.pt, calibration.json/.md, PNGs)."
    ),
    model: str | None = typer.Option(None, "--model", "-m", help="model.pt (default: shipped)."),
    recording: list[str] = typer.Option(  # noqa: B008
        [], "--recording", "-r", help="Recording with a reference to calibrate on (repeatable)."
    ),
    reference: str | None = typer.Option(
        None, "--reference", help="Reference for --recording: a TUM file or 'static'."
    ),
    data: list[str] = typer.Option(  # noqa: B008
        [], "--data", "-d", help="Or: labelled pair store(s) to calibrate on."
    ),
    split: list[str] = typer.Option(  # noqa: B008
        ["all"], "--split", "-s", help="Splits of --data to use; 'all' = every pair."
    ),
    method: str = typer.Option("temperature", "--method", help="temperature or platt."),
    max_scans: int | None = typer.Option(None, "--max-scans", help="Recordings: first N scans."),
    scan_topic: str | None = typer.Option(
        None, "--scan-topic", help="Recordings: LaserScan topic (CARMEN: FLASER, RLASER, ...)."
    ),
    odom_topic: str | None = typer.Option(None, "--odom-topic", help="Recordings: odometry topic."),
    reference_topic: str | None = typer.Option(
        None, "--reference-topic", help="Recordings: reference pose topic."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
) -> None:
    """Recalibrate a model (temperature or Platt, and its threshold) on labelled pairs.

    The pairs of --recording are labelled with its reference by the model's own label rule;
    the recalibrated model (the original plus a calibration block) is written to OUT/model.pt.
    """
    import json
    import tempfile

    from rich.markup import escape

    from scanguard.detect.calibrate import calibrate_detector, plot_reliability, save_calibrated
    from scanguard.detect.detector import FaultDetector
    from scanguard.fsutil import atomic_write_text

    if method not in _CALIBRATION_METHODS:
        raise ConfigError(f"--method must be temperature or platt, got {method!r}")
    if bool(recording) == bool(data):
        raise ConfigError("give --recording PATH (with a reference) or --data STORE, not both")
    topics = (scan_topic, odom_topic, reference_topic)
    if (any(t is not None for t in topics) or reference or max_scans) and not recording:
        raise ConfigError("--reference/--max-scans/--*-topic apply to --recording only")
    result = _result_dir(ctx, out, overwrite)  # before any long work
    det = FaultDetector.load(model)
    with contextlib.ExitStack() as stack:
        if recording:
            from scanguard.dataset import DatasetConfig
            from scanguard.dataset.build import build_from_recordings

            pairs_dir = stack.enter_context(tempfile.TemporaryDirectory(prefix="scanguard-cal-"))
            cfg_data: dict[str, Any] = {"matcher": getattr(det, "matchers", ("icp-paper",))[0]}
            if det.label_thresholds:  # the model's own label rule
                cfg_data["labels"] = det.label_thresholds
            cfg = DatasetConfig.from_dict(cfg_data, source=str(det.source))
            build_from_recordings(
                list(recording),
                pairs_dir,
                cfg,
                reference=reference,
                max_scans=max_scans,
                progress=False,
                scan_topic=scan_topic,
                odom_topic=odom_topic,
                reference_topic=reference_topic,
            )
            store: Any = pairs_dir
            where = ", ".join(Path(r).name for r in recording)
            if reference:
                where += (
                    f" (reference {Path(reference).name if reference != 'static' else reference})"
                )
            splits = None
        else:
            store = data if len(data) > 1 else data[0]
            where = ", ".join(Path(d).name for d in data)
            splits = None if "all" in split else list(split)
        fit = calibrate_detector(det, store, method=method, splits=splits, fitted_on=where)  # type: ignore[arg-type]
    report = {"model": det.source, **fit.report()}
    with result as tmp:
        save_calibrated(model, fit.calibration, Path(tmp) / "model.pt")
        atomic_write_text(Path(tmp) / "calibration.json", json.dumps(report, indent=2) + "\n")
        atomic_write_text(Path(tmp) / "calibration.md", _calibration_markdown(report))
        plot_reliability(
            [("before", fit.labels, fit.proba_before)],
            Path(tmp) / "reliability_before.png",
            title="before calibration",
        )
        plot_reliability(
            [("after", fit.labels, fit.proba_after)],
            Path(tmp) / "reliability_after.png",
            title=f"after {method} calibration",
        )
    table = _table(
        f"calibration ({method}) on {fit.calibration.n_pairs} labelled pairs",
        [("", False), *((k, True) for k in ("threshold", "accuracy", "bal. acc.", "F1", "ECE"))],
    )
    for key in ("before", "after"):
        m = report[key]
        table.add_row(
            key,
            _fmt(m["threshold"]),
            _fmt(m["accuracy"], pct=True),
            _fmt(m["balanced_accuracy"]),
            _fmt(m["f1"], pct=True),
            _fmt(m["ece"]),
        )
    console.print(table)
    cal = fit.calibration.to_dict()
    params = ", ".join(f"{k} {cal[k]:.4f}" for k in ("temperature", "a", "b") if k in cal)
    console.print(
        f"{params}; recalibrated model in [bold]{escape(str(Path(out) / 'model.pt'))}[/bold] "
        "(calibration.json, calibration.md, reliability_before.png, reliability_after.png)"
    )


export_app = typer.Typer(help="Export the fault-detection model.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@export_app.command("onnx")
@guarded
def export_onnx_cmd(
    out: str = typer.Option(..., "--out", "-o", help="Destination .onnx file."),
    model: str | None = typer.Option(None, "--model", "-m", help="model.pt (default: shipped)."),
) -> None:
    """Write the CNN as ONNX (inputs 'images' N x C x H x W in [0, 1] [+ 'metrics']; logits)."""
    from rich.markup import escape

    from scanguard.detect.detector import FaultDetector
    from scanguard.fsutil import check_output_path

    check_output_path(out, "file", suffixes=(".onnx",))  # before loading the model
    det = FaultDetector.load(model)
    path = det.export_onnx(out)
    h, w, c = det.input_shape
    metrics = ""
    if det.metric_names:
        metrics = (
            f" + metrics N x {len(det.metric_names)} (scanguard.detect.model.metric_inputs of "
            f"{', '.join(det.metric_names)})"
        )
    console.print(
        f"wrote [bold]{escape(str(path))}[/bold]: input images N x {c} x {h} x {w}{metrics}, "
        "output logits "
        f"N x 2 (fault = index 1, softmax then threshold {det.threshold:.3f}); "
        f"render style {det.style.kind} {det.style.size}px"
    )


# --- commands: run / demo (the guarded SLAM loop) ----------------------------------------------

_BASELINE_HELP = (
    "Classical gate of the <backend>+baseline instance: auto (shipped baseline, else the best "
    "one fitted on the dataset's train split, else GMapping's minimumScore rule), none, "
    "gmapping-default, a baseline name (residual, overlap, degeneracy, gmapping, metrics-model) "
    "or a JSON file."
)
_BACKEND_HELP = (
    "SLAM back end: gmapping (particle filter), graph (pose graph with judged loop closures) "
    "or frontend (scan-to-scan chaining). "
    "(default: gmapping)"
)
_RUNTIME_HELP = "CNN inference runtime: onnx or torch."
_ODOMETRY_HELP = (
    "auto (recorded odometry when usable, else none: a motion prior), recorded, or "
    "simulated (noisy odometry made from the reference; only when asked for). (default: auto)"
)
_PRIOR_HELP = (
    "Motion prior without odometry: zero-motion or constant-velocity (each back end "
    "extrapolates its own estimate). (default: zero-motion)"
)

_MOTION_HELP = (
    "What moves the back end between scans: odometry (the odometry above), or "
    "guarded-matches (the guard's scan-to-scan match where the gate accepts it, else the "
    "odometry; every scan is judged). (default: odometry)"
)
_MATCHER_HELP = "The guard's scan matcher (icp-paper, icp, plicp). (default: icp-paper)"


def _choice(option: str, value: str | None, allowed: tuple[str, ...]) -> str | None:
    """``value`` if it is one of ``allowed`` (None passes), else a one-line `ConfigError`."""
    from scanguard.errors import ConfigError

    if value is not None and value not in allowed:
        raise ConfigError(f"{option} must be one of {', '.join(allowed)}, not {value!r}")
    return value


def _run_config(
    config: str | None,
    *,
    backend: str | None = None,
    odometry: str | None = None,
    prior: str | None = None,
    motion: str | None = None,
    matcher: str | None = None,
    particles: int | None = None,
    seed: int | None = None,
    relations: str | None = None,
    max_scans: int | None = None,
    allow_other_matcher: bool = False,
) -> Any:
    """The `RunConfig` of a ``--config`` file (or the defaults) with the given options applied."""
    from scanguard.slam.run import RunConfig

    cfg = RunConfig.from_yaml(config) if config is not None else RunConfig()
    data = cfg.model_dump()
    if _choice("--backend", backend, ("gmapping", "graph", "frontend")) is not None:
        data["backend"] = backend
    if _choice("--odometry", odometry, ("auto", "recorded", "simulated")) is not None:
        data["odometry"] = odometry
    if _choice("--prior", prior, ("zero-motion", "constant-velocity")) is not None:
        data["prior"] = str(prior).replace("-", "_")
    if _choice("--motion", motion, ("odometry", "guarded-matches")) is not None:
        data["motion"] = str(motion).replace("-", "_")
    if matcher is not None:
        data["matcher"] = matcher
    if allow_other_matcher:  # the flag only turns it on; a --config file may already have
        data["allow_other_matcher"] = True
    from scanguard.matching import get_matcher

    # an unknown name (option or --config file) is a one-line error before any long work
    get_matcher(str(data["matcher"]))
    if relations is not None:
        data["relations"] = relations
    if max_scans is not None:
        data["max_scans"] = max_scans
    if particles is not None:
        data["gmapping"]["particles"] = particles
    if seed is not None:
        data["gmapping"]["seed"] = seed
    # validated by the model: --max-scans 1 or --particles 0 are one-line errors
    return RunConfig.from_dict(data, source="command-line options")


@contextlib.contextmanager
def _progress(total: int) -> Iterator[Callable[[Any, int, int], None]]:
    """A per-scan callback: a progress bar on a terminal, else a log line every 10 %."""
    from scanguard.logging_utils import progress

    with progress(total, "scans", logger=logger) as advance:

        def on_step(d: Any, acc: int, rej: int) -> None:
            advance(1, status=f"guard accepted {acc} / rejected {rej}")

        yield on_step


def _table(title: str, columns: list[tuple[str, bool]]) -> Any:
    """A rich table whose cells wrap (narrow terminals); ``(header, right-aligned)`` columns."""
    from rich import box
    from rich.table import Table

    t = Table(
        title=title, title_justify="left", box=box.SIMPLE_HEAD, padding=(0, 0), show_edge=False
    )
    for header, right in columns:
        t.add_column(header, justify="right" if right else "left", overflow="fold")
    return t


def _pipeline_report(res: Any, out: Any) -> None:
    from rich.markup import escape

    from scanguard.slam.run import judged_text

    c = res.counts
    console.print(
        f"[bold]{escape(str(res.name))}[/bold]: {res.n_scans} scans; odometry: "
        f"{res.odometry_source}; "
        f"matcher: {res.matcher}; back end: {res.backend}; reference: "
        f"{res.reference_kind or 'none'}",
        highlight=False,
    )
    console.print(f"guard: {judged_text(c)}", highlight=False)
    # one row per trajectory: the back end and its gate, the odometry and the matcher it used
    setup = [("back end", False), ("gate", False), ("odometry", False), ("matcher", False)]
    if res.errors:
        t = _table(
            "Trajectory errors against the reference (evo)",
            [*setup, ("ATE m", True), ("RPE m", True), ("RPE °", True), ("Δ RPE", True)],
        )
        for name, e in res.errors.items():
            s = res.setup(name)
            red = 0.0 if name == res.unguarded else res.rpe_reduction(name)
            t.add_row(
                *(s[k] for k, _ in setup),
                f"{e['ate_rmse']:.3f}",
                f"{e['rpe_trans_rmse']:.4f}",
                f"{e['rpe_rot_rmse_deg']:.2f}",
                f"{-100 * red:+.1f} %",
            )
        t.caption = (
            f"Δ RPE: RPE change against the unguarded {res.unguarded}; back end -: odometry alone"
        )
        console.print()
        console.print(t)
    for scope, table in res.relations.items():
        t = _table(
            f"Relations ({scope}), Kümmerle et al. 2009",
            [*setup, ("used", True), ("trans. m", True), ("rot. °", True)],
        )
        for name, r in table.items():
            s = res.setup(name)
            t.add_row(
                *(s[k] for k, _ in setup),
                f"{r.n_matched}/{r.n_selected}",
                f"{r.trans_mean:.3f} ± {r.trans_std:.3f}",
                f"{r.rot_mean_deg:.2f}",
            )
        t.caption = f"{res.relations_file}; mean ± std of the absolute errors (summary.md: all)"
        console.print()
        console.print(t)
    if res.relations and res.published:
        t = _table(
            "Published on this recording (Kümmerle et al. 2009, Table 1)",
            [("method", False), ("trans. m", True)],
        )
        for method, (mean, std) in res.published.items():
            t.add_row(method, f"{mean:.3f} ± {std:.3f}")
        console.print()
        console.print(t)
    if res.gates:
        t = _table(
            "Gates against reference labels (judged pairs, ambiguous excluded)",
            [
                ("gate", False),
                ("odometry", False),
                ("matcher", False),
                ("back end", False),
                ("pairs", True),
                ("acc.", True),
                ("prec.", True),
                ("recall", True),
            ],
        )
        for g in res.gates.values():
            t.add_row(
                g.name,
                res.odometry_source,
                res.matcher,
                res.backend,
                str(g.n),
                f"{g.accuracy:.3f}",
                f"{g.precision:.3f}",
                f"{g.recall:.3f}",
            )
        console.print()
        console.print(t)
    t = _table(
        "Per-scan latency (ms)",
        [
            ("stage", False),
            ("matcher", False),
            ("back end", False),
            ("median", True),
            ("p95", True),
        ],
    )
    for k, (m, p) in res.latency_ms.items():
        t.add_row(k, res.matcher, res.backend, f"{m:.2f}", f"{p:.2f}")
    console.print()
    console.print(t)
    console.print(
        f"outputs in [bold]{escape(str(out))}[/bold] (summary.md, metrics.json, "
        "maps_side_by_side.png, "
        "trajectories.png, map_*.pgm/.yaml, trajectory_*.tum)",
        highlight=False,
    )


def _pipeline_execute(
    seq: Any,
    result: Any,
    model: Any,
    cfg: Any,
    baseline: str = "auto",
    baseline_data: str | None = None,
    runtime: str = "onnx",
) -> Any:
    """Load the detector and the baseline, run the loop into ``result`` (a `ResultDir`)."""
    from scanguard.detect.detector import FaultDetector
    from scanguard.slam.run import resolve_baseline, run_recording

    _choice("--runtime", runtime, ("onnx", "torch"))
    detector = FaultDetector.load(model, backend=runtime, matcher=cfg.matcher)  # type: ignore[arg-type]
    with err_console.status("preparing the baseline gate"):
        judge, judge_info = resolve_baseline(baseline, baseline_data, cfg.matcher)
    console.print(f"baseline gate: {judge_info}", highlight=False, soft_wrap=True)
    n = len(seq) if cfg.max_scans is None else min(len(seq), cfg.max_scans)
    with result as tmp, _progress(n) as on_step:
        res = run_recording(
            seq,
            detector,
            tmp,
            config=cfg,
            baseline=judge,
            on_step=on_step,
            baseline_info=judge_info,
        )
    res.files = [result.final(p) for p in res.files]
    return res


def _check_odom_topic(seq: Any, odom_topic: str | None, cfg: Any) -> None:
    """Never ignore ``--odom-topic`` silently: fail when the run cannot use that odometry."""
    if odom_topic is None or cfg.motion == "guarded_matches":
        return
    if cfg.odometry == "simulated":
        raise ConfigError(
            f"--odom-topic {odom_topic}: not used with --odometry simulated (odometry made "
            "from the reference); drop one of the two"
        )
    if seq.odometry is None:
        raise ConfigError(f"--odom-topic {odom_topic}: {seq.name} has no odometry there")
    if seq.reference_kind == "corrected_log":
        raise ConfigError(
            f"--odom-topic {odom_topic}: {seq.name} is a corrected log, whose odometry is the "
            "corrected poses (the reference), so it is never used as odometry; drop "
            "--odom-topic (the run then uses a motion prior) or use the raw log"
        )


@app.command()
@guarded
@checked(seed=NON_NEGATIVE)  # --max-scans, --particles: checked by RunConfig
def run(
    ctx: typer.Context,
    recording: str = typer.Argument(..., help="Bag, bag folder or CARMEN log."),
    out: str = typer.Option("scanguard-run", "--out", "-o", help="Output folder."),
    scan_topic: str | None = typer.Option(None, help="LaserScan topic / CARMEN laser type."),
    odom_topic: str | None = typer.Option(None, help="Odometry topic."),
    reference_topic: str | None = typer.Option(None, help="Reference pose topic."),
    reference: str | None = typer.Option(
        None, help="TUM file with reference poses, or 'static' (the sensor never moved)."
    ),
    lenient: bool = typer.Option(
        False, "--lenient", help="Skip malformed lines/messages (counted) instead of refusing."
    ),
    corrected: bool | None = typer.Option(
        None,
        "--corrected/--not-corrected",
        help="CARMEN: the log's poses are SLAM-corrected (reference), or raw odometry. "
        "(default: from the file name or its NEFF lines)",
    ),
    backend: str | None = typer.Option(None, "--backend", help=_BACKEND_HELP),
    runtime: str = typer.Option("onnx", "--runtime", help=_RUNTIME_HELP),
    odometry: str | None = typer.Option(None, "--odometry", help=_ODOMETRY_HELP),
    prior: str | None = typer.Option(None, "--prior", help=_PRIOR_HELP),
    motion: str | None = typer.Option(None, "--motion", help=_MOTION_HELP),
    matcher: str | None = typer.Option(None, "--matcher", help=_MATCHER_HELP),
    particles: int | None = typer.Option(
        None, "--particles", help="GMapping particles. (default: 30)"
    ),
    seed: int | None = typer.Option(
        None, "--seed", help="Seed of the particle filter (same seed, same run). (default: 0)"
    ),
    relations: str | None = typer.Option(
        None,
        "--relations",
        help="Kümmerle reference relations file (default: <stem>.relations next to a "
        ".clf/.clf.gz/.log recording, if there is one).",
    ),
    max_scans: int | None = typer.Option(
        None, "--max-scans", help="Only use the first N scans (N >= 2)."
    ),
    model: str | None = typer.Option(None, help="Model file (default: the shipped model)."),
    config: str | None = typer.Option(
        None, help="RunConfig YAML (see config.yaml of a run); options override it."
    ),
    baseline: str = typer.Option("auto", help=_BASELINE_HELP),
    baseline_data: str | None = typer.Option(
        None, help="Pair store to fit the baseline on (default: data/paper of the checkout)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    allow_other_matcher: bool = typer.Option(
        False,
        "--allow-other-matcher",
        help="Judge the matches of a matcher the model was not trained for (its verdicts are "
        "then uncalibrated); refused otherwise.",
    ),
) -> None:
    """Run the guarded SLAM loop over a recording; write trajectories, maps and metrics."""
    from scanguard.io import read_sequence
    from scanguard.slam.run import find_relations

    _choice("--runtime", runtime, ("onnx", "torch"))
    cfg = _run_config(
        config,
        backend=backend,
        odometry=odometry,
        prior=prior,
        motion=motion,
        matcher=matcher,
        particles=particles,
        seed=seed,
        relations=relations,
        max_scans=max_scans,
        allow_other_matcher=allow_other_matcher,
    )
    result = _result_dir(ctx, out, overwrite)  # before reading the recording
    if cfg.relations is None:
        found = find_relations(recording)
        if found is not None:
            console.print(
                f"relations: {found} (found next to the recording)",
                highlight=False,
                soft_wrap=True,
            )
            cfg.relations = str(found)
    seq = read_sequence(
        recording,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
        reference=reference,
        reader_options=None if corrected is None else {"corrected": corrected},
        lenient=lenient,
    )
    _check_odom_topic(seq, odom_topic, cfg)
    res = _pipeline_execute(seq, result, model, cfg, baseline, baseline_data, runtime)
    _pipeline_report(res, out)


@app.command()
@guarded
@checked(seed=NON_NEGATIVE)
def demo(
    ctx: typer.Context,
    out: str = typer.Option("scanguard-demo", "--out", "-o", help="Output folder."),
    fast: bool = typer.Option(
        False, "--fast", help="A few dozen scans (for CI; also when the CI env var is set)."
    ),
    seed: int = typer.Option(7, help="Simulation seed."),
    backend: str | None = typer.Option(None, "--backend", help=_BACKEND_HELP),
    runtime: str = typer.Option("onnx", "--runtime", help=_RUNTIME_HELP),
    particles: int | None = typer.Option(
        None, "--particles", help="GMapping particles. (default: 30)"
    ),
    model: str | None = typer.Option(None, help="Model file (default: the shipped model)."),
    baseline: str = typer.Option("auto", help=_BASELINE_HELP),
    baseline_data: str | None = typer.Option(
        None, help="Pair store to fit the baseline on (default: data/paper of the checkout)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
) -> None:
    """Simulate a crowded scene and run the guarded SLAM loop on it (no downloads)."""
    from scanguard.slam.run import DEMO_GMAPPING_LSKIP, DEMO_SCENARIO, demo_sequence

    _choice("--runtime", runtime, ("onnx", "torch"))
    cfg = _run_config(None, backend=backend, particles=particles)
    cfg.gmapping = cfg.gmapping.model_copy(update={"lskip": DEMO_GMAPPING_LSKIP})
    result = _result_dir(ctx, out, overwrite)  # before simulating
    fast = fast or bool(os.environ.get("CI"))
    with err_console.status(f"simulating the {DEMO_SCENARIO} scene"):
        seq = demo_sequence(fast=fast, seed=seed)
    res = _pipeline_execute(seq, result, model, cfg, baseline, baseline_data, runtime)
    _pipeline_report(res, out)


@app.command("run-many")
@guarded
@checked(seed=NON_NEGATIVE, workers=AT_LEAST_ONE)
def run_many(
    ctx: typer.Context,
    recordings: str = typer.Argument(
        ..., help="Folder (searched recursively) or glob pattern of recordings."
    ),
    out: str = typer.Option(..., "--out", "-o", help="Output folder (resumable)."),
    executor: str = typer.Option("local", "--executor", help="Where tasks run: local or ray."),
    address: str | None = typer.Option(
        None, "--address", help="Ray cluster address (--executor ray; default: a local Ray)."
    ),
    workers: int | None = typer.Option(
        None, "--workers", "-j", help="Parallel recordings. (default: 1; Ray: all CPUs)"
    ),
    lenient: bool = typer.Option(
        False, "--lenient", help="Skip malformed lines/messages (counted) instead of refusing."
    ),
    backend: str | None = typer.Option(None, "--backend", help=_BACKEND_HELP),
    runtime: str = typer.Option("onnx", "--runtime", help=_RUNTIME_HELP),
    odometry: str | None = typer.Option(None, "--odometry", help=_ODOMETRY_HELP),
    prior: str | None = typer.Option(None, "--prior", help=_PRIOR_HELP),
    motion: str | None = typer.Option(None, "--motion", help=_MOTION_HELP),
    matcher: str | None = typer.Option(None, "--matcher", help=_MATCHER_HELP),
    particles: int | None = typer.Option(
        None, "--particles", help="GMapping particles. (default: 30)"
    ),
    seed: int | None = typer.Option(
        None, "--seed", help="Seed of the particle filter (same seed, same run). (default: 0)"
    ),
    max_scans: int | None = typer.Option(
        None, "--max-scans", help="Only use the first N scans of each recording (N >= 2)."
    ),
    model: str | None = typer.Option(None, help="Model file (default: the shipped model)."),
    config: str | None = typer.Option(
        None, help="RunConfig YAML (see config.yaml of a run); options override it."
    ),
    baseline: str = typer.Option("auto", help=_BASELINE_HELP),
    baseline_data: str | None = typer.Option(
        None, help="Pair store to fit the baseline on (default: data/paper of the checkout)."
    ),
    allow_other_matcher: bool = typer.Option(
        False,
        "--allow-other-matcher",
        help="Judge the matches of a matcher the model was not trained for.",
    ),
) -> None:
    """Run the guarded SLAM loop over many recordings (one task each); one merged table.

    Each recording gets OUT/<stem>/ (as `scanguard run`); a rerun skips complete ones; a
    failing recording is reported in OUT/results.csv and OUT/results.md, and the exit code
    is then 1.
    """
    from rich.markup import escape

    from scanguard.apps.run_many import find_recordings
    from scanguard.apps.run_many import run_many as run_many_
    from scanguard.fsutil import check_output_path
    from scanguard.runtime.executor import make_executor

    _choice("--runtime", runtime, ("onnx", "torch"))
    _choice("--executor", executor, ("local", "ray"))
    cfg = _run_config(
        config,
        backend=backend,
        odometry=odometry,
        prior=prior,
        motion=motion,
        matcher=matcher,
        particles=particles,
        seed=seed,
        max_scans=max_scans,
        allow_other_matcher=allow_other_matcher,
    )
    if cfg.relations is not None:
        raise ConfigError(
            "run-many: the config names one relations file for every recording; drop "
            "'relations' (each recording uses <stem>.relations next to it)"
        )
    pool = make_executor(executor, address=address, workers=workers)
    out_path = check_output_path(out, kind="dir")
    found = find_recordings(recordings, exclude=out_path)
    console.print(f"{len(found)} recordings, executor {executor}", highlight=False)
    record = _command_record(ctx)
    record = {"command": record["command"], "cwd": record["cwd"]}

    def show(res: Any) -> None:
        tail = f": {res.error}" if res.error else ""
        console.print(
            f"{res.status:8s} {escape(str(res.recording))}{escape(tail)}",
            highlight=False,
            soft_wrap=True,
        )

    results = run_many_(
        found,
        out_path,
        cfg,
        pool,
        model=model,
        runtime=runtime,
        baseline=baseline,
        baseline_data=baseline_data,
        lenient=lenient,
        record=record,
        on_result=show,
    )
    console.print(
        f"table in [bold]{escape(str(Path(out) / 'results.md'))}[/bold] (and results.csv)",
        highlight=False,
    )
    failed = sum(r.status == "failed" for r in results)
    if failed:
        _fail(f"{failed} of {len(results)} recordings failed (see {Path(out) / 'results.md'})")
