"""Command-line interface: parses arguments, calls the library, prints results.

Heavy modules (torch, rosbags, matplotlib) are imported inside the commands so that
``scanguard --help`` stays fast.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console

from scanguard import __version__
from scanguard.errors import ScanGuardError

app = typer.Typer(
    name="scanguard",
    help="Detect faulty 2D LiDAR scan matches with a CNN and keep SLAM honest.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)
logger = logging.getLogger("scanguard.cli")

F = TypeVar("F", bound=Callable[..., Any])


def guarded(fn: F) -> F:
    """Turn expected errors (`ScanGuardError`) into one red line on stderr and exit code 1."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ScanGuardError as exc:
            err_console.print(f"[bold red]error:[/bold red] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None

    return wrapper  # type: ignore[return-value]


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
) -> None:
    """Summarise a recording: scans, beams, field of view, rate, odometry, reference, topics."""
    from rich.table import Table

    from scanguard.io import read_sequence, summarize

    seq = read_sequence(
        path,
        format=format,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        reference_topic=reference_topic,
        reference=reference,
    )
    s = summarize(seq)
    unknown = "unknown (see note)" if s["stamps_note"] else "unknown"
    table = Table(title=f"{path}", show_header=False, title_justify="left")
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("format", f"{s['format']} (sensor: {s['sensor']})")
    table.add_row("scans", str(s["scans"]))
    table.add_row("beams", " / ".join(str(b) for b in s["beams"]))
    table.add_row("field of view", f"{s['fov_deg']:.1f} deg")
    table.add_row("range limits", f"{s['range_min']:.2f} .. {s['range_max']:.2f} m")
    table.add_row("rate", unknown if s["rate_hz"] is None else f"{s['rate_hz']:.2f} Hz")
    table.add_row("duration", unknown if s["duration_s"] is None else f"{s['duration_s']:.1f} s")
    table.add_row("invalid beams", f"{100 * s['invalid_fraction']:.1f} %")
    table.add_row("odometry", f"yes ({s['odometry_source']})" if s["odometry"] else "no")
    ref = f"yes ({s['reference_kind']}: {s['reference_source']})" if s["reference"] else "no"
    table.add_row("reference", ref)
    off = s["laser_offset"]
    table.add_row("laser offset", f"x {off[0]:.3f} m, y {off[1]:.3f} m, yaw {off[2]:.3f} rad")
    topics = "\n".join(
        f"{name}  [dim]{t['type']}[/dim]  {t['count']}" for name, t in sorted(s["topics"].items())
    )
    table.add_row("topics found", topics or "-")
    if s["stamps_note"]:
        table.add_row("note", f"[yellow]{s['stamps_note']}[/yellow]")
    console.print(table)


# --- commands: simulate (sim) ----------------------------------------------------------------


@app.command()
@guarded
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
    """Simulate a crowded LiDAR recording with exact ground truth and write it as a ROS 2 bag."""
    from pathlib import Path

    import numpy as np
    import yaml
    from rich.table import Table

    from scanguard.config import save_config
    from scanguard.errors import ConfigError
    from scanguard.sim import simulate_run

    if output is None and preview is None:
        raise ConfigError("nothing to do: give --output (bag) and/or --preview (PNG)")
    overrides: dict[str, object] = {}
    for item in set_:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected key=value, e.g. people.count=20")
        overrides[key.strip().replace(".", "__")] = yaml.safe_load(value)
    for key, val in {
        "stride": stride,
        "scan_rate_hz": scan_rate,
        "people__count": people,
        "sensor__model": sensor,
    }.items():
        if val is not None:
            overrides[key] = val
    res = simulate_run(scenario, seed=seed, duration=duration, progress=True, **overrides)
    seq = res.sequence
    written = []
    if output is not None:
        from scanguard.io import write_sequence

        out = write_sequence(seq, output)
        cfg_path = save_config(res.config, out.parent, name=f"{Path(output).stem}.scenario.yaml")
        written += [str(out), str(cfg_path)]
    if preview is not None:
        from scanguard.sim.preview import save_preview

        written.append(str(save_preview(res, preview)))
    ranges = seq.ranges_matrix()
    # simulate() always sets both; the checks keep the types honest
    assert seq.reference is not None and seq.sensor is not None
    steps = np.diff(seq.reference, axis=0)
    table = Table(title=f"simulated {res.config.name} (seed {seed})", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("scans", f"{len(seq)} at {seq.rate_hz or 0:.1f} Hz, {seq.sensor.n_beams} beams")
    table.add_row("sensor", f"{seq.sensor.name}, {seq.sensor.fov_deg:.0f} deg")
    table.add_row("agents", str(seq.metadata["n_people"]))
    table.add_row("robot path", f"{np.hypot(steps[:, 0], steps[:, 1]).sum():.1f} m")
    table.add_row("inf beams", f"{100 * np.isinf(ranges).mean():.1f} %")
    table.add_row("written", "\n".join(written))
    console.print(table)


# --- commands: dataset (dataset) -------------------------------------------------------------

dataset_app = typer.Typer(
    help="Build, inspect and export labelled scan-pair datasets.", no_args_is_help=True
)
app.add_typer(dataset_app, name="dataset")


@dataset_app.command("build")
@guarded
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
    workers: int = typer.Option(1, "--workers", "-j", help="Parallel sequence builds."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Rebuild files of another config."),
) -> None:
    """Simulate + match + label (with --config), or label recordings (with --recording)."""
    import time

    from rich.table import Table

    from scanguard.dataset import DatasetConfig, build_dataset, build_from_recording
    from scanguard.errors import ConfigError

    cfg = DatasetConfig.from_yaml(config) if config else DatasetConfig()
    if matcher:
        cfg = cfg.model_copy(update={"matcher": matcher})
        cfg = DatasetConfig.from_dict(cfg.model_dump(), source="--matcher")
    valid_initial = ("identity", "odometry", "simulated_odometry", "auto")
    if initial is not None and initial not in valid_initial:
        raise ConfigError(f"--initial must be one of {', '.join(valid_initial)}, got {initial!r}")
    t0 = time.perf_counter()
    if recording:
        for rec_path in recording:
            summary = build_from_recording(
                rec_path,
                out,
                cfg,
                reference=reference,
                initial_guess=initial,  # type: ignore[arg-type]
                max_scans=max_scans,
                overwrite=overwrite,
            )
    else:
        if not config:
            raise ConfigError("give --config (simulated build) or --recording PATH")
        summary = build_dataset(cfg, out, overwrite=overwrite, workers=workers)
    table = Table(title=f"{out}: {len(summary.built)} built, {len(summary.skipped)} resumed")
    for col in ("sequence", "environment", "split", "pairs", "normal", "fault", "ambiguous"):
        table.add_column(col, justify="right" if col in ("pairs", "normal", "fault") else "left")
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


@dataset_app.command("stats")
@guarded
def dataset_stats(
    store: list[str] = typer.Argument(..., help="Dataset directories and/or pair files."),  # noqa: B008
    out: str | None = typer.Option(
        None, "--out", "-o", help="Histogram/JSON directory (default: <first store>/stats)."
    ),
) -> None:
    """Per-environment normal/fault/ambiguous counts and error histograms (PNG)."""
    from pathlib import Path

    from rich.table import Table

    from scanguard.dataset import PairStore, write_stats

    ps = PairStore.open(store)
    first = Path(store[0])
    dest = Path(out) if out else (first if first.is_dir() else first.parent) / "stats"
    rows, js = write_stats(ps, dest)
    table = Table(title=f"{len(ps)} pairs")
    cols = ("environment", "splits", "sequences", "pairs", "normal", "fault", "ambiguous")
    for col in (*cols, "fault rate"):
        table.add_column(col, justify="left" if col in ("environment", "splits") else "right")
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
def dataset_export_png(
    store: list[str] = typer.Argument(..., help="Dataset directories and/or pair files."),  # noqa: B008
    out: str = typer.Option(..., "--out", "-o", help="Root of <env>/<class>/*.png."),
    per_class: int | None = typer.Option(
        None, "--per-class", "-n", help="At most N images per environment and class."
    ),
    kind: str = typer.Option("paper", "--style", help="paper | occupancy | metric."),
    size: int = typer.Option(256, "--size", help="Image side (px)."),
    ambiguous: bool = typer.Option(False, "--ambiguous", help="Also export ambiguous pairs."),
    seed: int = typer.Option(0, "--seed", help="Seed of the per-class subsample."),
) -> None:
    """Write pair images in the paper's folder layout (<env>/normal, <env>/fault)."""
    from scanguard.dataset import PairStore, export_png
    from scanguard.render import RenderStyle

    style = RenderStyle.from_dict({"kind": kind, "size": size}, source="--style/--size")
    written = export_png(
        PairStore.open(store),
        out,
        style,
        per_class=per_class,
        include_ambiguous=ambiguous,
        seed=seed,
        progress=True,
    )
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

    dest = merge_stores(sources, out)
    console.print(f"{dest}: {len(PairStore.open(dest))} pairs")


# --- commands: train / evaluate / export (model) ---------------------------------------------


@app.command()
@guarded
def train(
    data: list[str] = typer.Option(  # noqa: B008
        ..., "--data", "-d", help="Pair store(s): dataset folder(s) and/or .h5 files."
    ),
    out: str = typer.Option(..., "--out", "-o", help="Output folder (model.pt, curves.png, ...)."),
    config: str | None = typer.Option(None, "--config", "-c", help="Training YAML."),
    preset: str | None = typer.Option(
        None, "--preset", help="paper|compact|multiscale|cnn+metrics|compact128|tiny."
    ),
    epochs: int | None = typer.Option(None, "--epochs", help="Override the epoch count."),
    max_train: int | None = typer.Option(None, "--max-train", help="Seeded training subset."),
    seed: int | None = typer.Option(None, "--seed", help="Override the seed."),
    threads: int | None = typer.Option(None, "--threads", help="Torch threads."),
) -> None:
    """Train the fault-detection CNN (best epoch on the validation split)."""
    import os

    # idle OpenMP workers must sleep, not spin: the machine is shared with other jobs
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from rich.table import Table

    from scanguard.train import TrainConfig
    from scanguard.train import train as run_training

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
    res = run_training(cfg, data if len(data) > 1 else data[0], out)
    t = Table(title=f"training {res.checkpoint['model_config']['preset']}")
    for col in ("epoch", "train loss", "train acc", "val loss", "val acc", "img/s"):
        t.add_column(col, justify="right")
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
        f"model in [bold]{out}/model.pt[/bold] (curves.png, history.json, config.yaml)"
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
) -> None:
    """Paper Table 2 per environment (fault = positive) + baselines; ROC/confusion PNGs."""
    from rich.table import Table

    from scanguard.evaluate import evaluate_store

    names: list[str] | None
    if baselines == "all":
        names = None
    elif baselines == "none":
        names = []
    else:
        names = [b.strip() for b in baselines.split(",") if b.strip()]
    res = evaluate_store(
        model,
        data if len(data) > 1 else data[0],
        out,
        splits=None if "all" in split else split,
        environments=environment or None,
        baselines=names,
        baseline_store=(baseline_data if len(baseline_data) > 1 else baseline_data[0])
        if baseline_data
        else None,
        backend=backend,
    )
    t = Table(title="fault detection (positive class: fault)")
    cols = ("method", "environment", "TP", "FN", "FP", "TN", "recall", "precision", "accuracy")
    for col in (*cols, "F1", "AUC", "threshold", "ambiguous (flagged)"):
        t.add_column(col, justify="left" if col in ("method", "environment") else "right")
    last = None
    for r in res.rows:
        if last is not None and r["method"] != last:
            t.add_section()
        last = r["method"]
        t.add_row(
            r["method"],
            r["environment"],
            *(str(r[k]) for k in ("TP", "FN", "FP", "TN")),
            *(_fmt(r[k], pct=True) for k in ("recall", "precision", "accuracy", "f1")),
            _fmt(r["auc"]),
            _fmt(r["threshold"]),
            f"{r['n_ambiguous']} ({_fmt(r['ambiguous_flagged'], pct=True)})",
        )
    console.print(t)
    if out:
        console.print(f"results in [bold]{out}[/bold] (results.json, results.csv, roc.png, ...)")


export_app = typer.Typer(help="Export the fault-detection model.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@export_app.command("onnx")
@guarded
def export_onnx_cmd(
    out: str = typer.Option(..., "--out", "-o", help="Destination .onnx file."),
    model: str | None = typer.Option(None, "--model", "-m", help="model.pt (default: shipped)."),
) -> None:
    """Write the CNN as ONNX (inputs 'images' N x C x H x W in [0, 1] [+ 'metrics']; logits)."""
    from scanguard.detector import FaultDetector

    det = FaultDetector.load(model)
    path = det.export_onnx(out)
    h, w, c = det.input_shape
    metrics = ""
    if det.metric_names:
        metrics = (
            f" + metrics N x {len(det.metric_names)} (scanguard.model.metric_inputs of "
            f"{', '.join(det.metric_names)})"
        )
    console.print(
        f"wrote [bold]{path}[/bold]: input images N x {c} x {h} x {w}{metrics}, output logits "
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
    "SLAM back end: gmapping (particle filter) or frontend (scan-to-scan chaining). "
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
) -> Any:
    """The `RunConfig` of a ``--config`` file (or the defaults) with the given options applied."""
    from scanguard.slam.run import RunConfig

    cfg = RunConfig.from_yaml(config) if config is not None else RunConfig()
    data = cfg.model_dump()
    if _choice("--backend", backend, ("gmapping", "frontend")) is not None:
        data["backend"] = backend
    if _choice("--odometry", odometry, ("auto", "recorded", "simulated")) is not None:
        data["odometry"] = odometry
    if _choice("--prior", prior, ("zero-motion", "constant-velocity")) is not None:
        data["prior"] = str(prior).replace("-", "_")
    if _choice("--motion", motion, ("odometry", "guarded-matches")) is not None:
        data["motion"] = str(motion).replace("-", "_")
    if matcher is not None:
        from scanguard.matching import get_matcher

        get_matcher(matcher)  # an unknown name is a one-line error before any long work
        data["matcher"] = matcher
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
    if err_console.is_terminal:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

        with Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=err_console,
            transient=True,
        ) as bar:
            task = bar.add_task("scans", total=total)

            def on_bar(d: Any, acc: int, rej: int) -> None:
                bar.update(task, advance=1, description=f"accepted {acc} / rejected {rej}")

            yield on_bar
        return
    every = max(1, math.ceil(total / 10))
    seen = 0
    t0 = time.perf_counter()

    def on_log(d: Any, acc: int, rej: int) -> None:
        nonlocal seen
        seen += 1
        if seen % every == 0 or seen == total:
            logger.info(
                "scans %d/%d (%d %%), guard accepted %d / rejected %d, %.0f s",
                seen,
                total,
                round(100 * seen / max(total, 1)),
                acc,
                rej,
                time.perf_counter() - t0,
            )

    yield on_log


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
    from scanguard.slam.run import judged_text

    c = res.counts
    console.print(
        f"[bold]{res.name}[/bold]: {res.n_scans} scans; odometry: {res.odometry_source}; "
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
        f"outputs in [bold]{out}[/bold] (summary.md, metrics.json, maps_side_by_side.png, "
        "trajectories.png, map_*.pgm/.yaml, trajectory_*.tum)",
        highlight=False,
    )


def _pipeline_execute(
    seq: Any,
    out: Any,
    model: Any,
    cfg: Any,
    baseline: str = "auto",
    baseline_data: str | None = None,
    runtime: str = "onnx",
) -> Any:
    from scanguard.detector import FaultDetector
    from scanguard.slam.run import resolve_baseline, run_recording

    _choice("--runtime", runtime, ("onnx", "torch"))
    detector = FaultDetector.load(model, backend=runtime)  # type: ignore[arg-type]
    with err_console.status("preparing the baseline gate"):
        judge, judge_info = resolve_baseline(baseline, baseline_data)
    console.print(f"baseline gate: {judge_info}", highlight=False)
    n = len(seq) if cfg.max_scans is None else min(len(seq), cfg.max_scans)
    with _progress(n) as on_step:
        return run_recording(
            seq,
            detector,
            out,
            config=cfg,
            baseline=judge,
            on_step=on_step,
            baseline_info=judge_info,
        )


@app.command()
@guarded
def run(
    recording: str = typer.Argument(..., help="Bag, bag folder or CARMEN log."),
    out: str = typer.Option("scanguard-run", "--out", "-o", help="Output folder."),
    scan_topic: str | None = typer.Option(None, help="LaserScan topic / CARMEN laser type."),
    odom_topic: str | None = typer.Option(None, help="Odometry topic."),
    reference_topic: str | None = typer.Option(None, help="Reference pose topic."),
    reference: str | None = typer.Option(
        None, help="TUM file with reference poses, or 'static' (the sensor never moved)."
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
) -> None:
    """Run the guarded SLAM loop over a recording; write trajectories, maps and metrics."""
    from scanguard.io import read_sequence
    from scanguard.slam.run import find_relations

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
    )
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
    )
    res = _pipeline_execute(seq, Path(out), model, cfg, baseline, baseline_data, runtime)
    _pipeline_report(res, out)


@app.command()
@guarded
def demo(
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
) -> None:
    """Simulate a crowded scene and run the guarded SLAM loop on it (no downloads)."""
    import os

    from scanguard.slam.run import DEMO_GMAPPING_LSKIP, DEMO_SCENARIO, demo_sequence

    cfg = _run_config(None, backend=backend, particles=particles)
    cfg.gmapping = cfg.gmapping.model_copy(update={"lskip": DEMO_GMAPPING_LSKIP})
    fast = fast or bool(os.environ.get("CI"))
    with err_console.status(f"simulating the {DEMO_SCENARIO} scene"):
        seq = demo_sequence(fast=fast, seed=seed)
    res = _pipeline_execute(seq, Path(out), model, cfg, baseline, baseline_data, runtime)
    _pipeline_report(res, out)
