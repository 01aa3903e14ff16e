"""Options shared by several commands, each declared once (``Annotated`` aliases).

A command takes an option by annotating a parameter with its alias, and gives the default
there: ``out: Out = "scanguard-run"``; an alias without a default is a required option.
Groups: recording options (what to read from a recording), loop options (the guarded SLAM
loop of ``run``, ``demo`` and ``run-many``), executor options (where tasks run) and output
options.
"""

from __future__ import annotations

from typing import Annotated

import typer

# --- recording options: which streams of a recording, and how strictly it is read -------------

ScanTopic = Annotated[
    str | None,
    typer.Option(
        "--scan-topic",
        metavar="TOPIC",
        help="LaserScan topic (CARMEN: laser type FLASER, RLASER, ROBOTLASER1).",
    ),
]
OdomTopic = Annotated[
    str | None, typer.Option("--odom-topic", metavar="TOPIC", help="Odometry topic.")
]
ReferenceTopic = Annotated[
    str | None,
    typer.Option(
        "--reference-topic", metavar="TOPIC", help="Reference pose topic (Odometry or PoseStamped)."
    ),
]
Reference = Annotated[
    str | None,
    typer.Option(
        "--reference",
        metavar="PATH",
        help="TUM file with reference poses, or 'static' (the sensor never moved).",
    ),
]
Lenient = Annotated[
    bool,
    typer.Option("--lenient", help="Skip malformed lines/messages (counted) instead of refusing."),
]
Corrected = Annotated[
    bool | None,
    typer.Option(
        "--corrected/--not-corrected",
        help="CARMEN: the log's poses are SLAM-corrected (reference), or raw odometry. "
        "(default: from the file name or its NEFF lines)",
    ),
]
Recordings = Annotated[
    list[str],
    typer.Option(
        "--recording", "-r", metavar="PATH", help="A recording with a reference (repeatable)."
    ),
]
MaxScans = Annotated[
    int | None,
    typer.Option("--max-scans", help="Only use the first N scans of each recording (N >= 2)."),
]

NoCompare = Annotated[
    bool,
    typer.Option(
        "--no-compare",
        help="Run the main (guarded) instance alone: no unguarded, classical or oracle "
        "comparison. Each comparison is a whole back-end instance of its own (about the cost "
        "of the main one again; on a machine with a second core, a long graph run puts them "
        "in a worker process, config instance_processes); the main result is the same "
        "either way.",
    ),
]

RelationTolerance = Annotated[
    float | None,
    typer.Option(
        "--relation-tolerance",
        metavar="SECONDS",
        help="A relation stamp takes the nearest scan stamp within this many seconds "
        "(default 0.001).",
    ),
]

# --- model and data options ---------------------------------------------------------------------

Model = Annotated[
    str | None,
    typer.Option("--model", "-m", metavar="PATH", help="Model file (default: the shipped model)."),
]
SelfCalibrate = Annotated[
    bool,
    typer.Option(
        "--self-calibrate",
        help="First recalibrate the model on this recording, no reference needed (as "
        "`calibrate --self`; costs a first pass), into OUT/self_calibration/, and run with it.",
    ),
]
RelationsFile = Annotated[
    str | None,
    typer.Option("--relations", metavar="PATH", help="Kümmerle reference relations file "
                 "(default: <stem>.relations next to a .clf/.clf.gz/.log recording, if any)."),
]  # fmt: skip
Data = Annotated[
    list[str],
    typer.Option(
        "--data",
        "-d",
        metavar="PATH",
        help="Pair store(s): dataset folder(s) and/or .h5 files (repeatable).",
    ),
]
Split = Annotated[
    list[str],
    typer.Option(
        "--split", "-s", metavar="NAME", help="Split(s) of the stores to use; 'all' = every pair."
    ),
]
Config = Annotated[
    str | None,
    typer.Option(
        "--config",
        "-c",
        metavar="PATH",
        help="YAML config (e.g. configs/*.yaml, a run's config.yaml); options override it.",
    ),
]

# --- loop options: the guarded SLAM loop (run, demo, run-many) ---------------------------------

Backend = Annotated[
    str | None,
    typer.Option(
        "--backend",
        metavar="NAME",
        help="SLAM back end: gmapping (particle filter), graph (pose graph with judged loop "
        "closures) or frontend (scan-to-scan chaining). (default: graph)",
    ),
]
Runtime = Annotated[
    str, typer.Option("--runtime", metavar="NAME", help="CNN inference runtime: onnx or torch.")
]
Odometry = Annotated[
    str | None,
    typer.Option(
        "--odometry",
        metavar="NAME",
        help="auto (recorded odometry when usable, else none: a motion prior), recorded, or "
        "simulated (noisy odometry made from the reference; only when asked for). "
        "(default: auto)",
    ),
]
Prior = Annotated[
    str | None,
    typer.Option(
        "--prior",
        metavar="NAME",
        help="Motion prior without odometry: zero-motion or constant-velocity (each back end "
        "extrapolates its own estimate). (default: zero-motion)",
    ),
]
Motion = Annotated[
    str | None,
    typer.Option(
        "--motion",
        metavar="NAME",
        help="What moves the back end between scans: fused (the wheels, the judged matches "
        "and a constant-velocity prediction by their information; every scan is judged), "
        "odometry (the odometry above: the paper's loop), or guarded-matches (the guard's "
        "scan-to-scan match where the gate accepts it, else the odometry). (default: fused)",
    ),
]
Matcher = Annotated[
    str | None,
    typer.Option(
        "--matcher",
        metavar="NAME",
        help="The guard's scan matcher (icp-paper, icp, plicp). (default: icp-paper)",
    ),
]
Particles = Annotated[
    int | None, typer.Option("--particles", help="GMapping particles. (default: 30)")
]
FilterSeed = Annotated[
    int | None,
    typer.Option("--seed", help="Seed of the particle filter (same seed, same run). (default: 0)"),
]
Baseline = Annotated[
    str,
    typer.Option(
        "--baseline",
        metavar="NAME",
        help="Classical gate of the <backend>+baseline instance: auto (shipped baseline, else "
        "the best one fitted on the dataset's train split, else GMapping's minimumScore rule), "
        "none, gmapping-default, a baseline name (residual, overlap, degeneracy, gmapping, "
        "metrics-model) or a JSON file.",
    ),
]
BaselineData = Annotated[
    str | None,
    typer.Option(
        "--baseline-data",
        metavar="PATH",
        help="Pair store to fit the baseline on (default: data/paper of the checkout).",
    ),
]
AllowOtherMatcher = Annotated[
    bool,
    typer.Option(
        "--allow-other-matcher",
        help="Judge the matches of a matcher the model was not trained for (its verdicts are "
        "then uncalibrated); refused otherwise.",
    ),
]

# --- executor options: where the tasks of a many-input command run ----------------------------

Executor = Annotated[
    str, typer.Option("--executor", metavar="NAME", help="Where tasks run: local or ray.")
]
Address = Annotated[
    str | None,
    typer.Option(
        "--address",
        metavar="ADDRESS",
        help="Ray cluster address (--executor ray; default: a local Ray).",
    ),
]
Workers = Annotated[
    int | None,
    typer.Option("--workers", "-j", help="Parallel tasks. (default: 1; Ray: all CPUs)"),
]

# --- output options -------------------------------------------------------------------------------

_OUT = typer.Option("--out", "-o", metavar="PATH", help="Output folder.")
Out = Annotated[str, _OUT]
#: ``--out`` of a command that writes files only when it is given.
OptionalOut = Annotated[str | None, _OUT]
Overwrite = Annotated[
    bool,
    typer.Option(
        "--overwrite",
        help="Write into an existing folder that scanguard did not create (only files of the "
        "same names are replaced; other files are kept).",
    ),
]

#: ``--overwrite`` of a command that writes one file (``export onnx -o FILE``).
OverwriteFile = Annotated[
    bool,
    typer.Option(
        "--overwrite",
        help="Replace an existing file at --out (a symbolic link there is followed).",
    ),
]

# --- view options: the run seen in Foxglove or rviz (run, demo) --------------------------------

Mcap = Annotated[
    bool,
    typer.Option(
        "--mcap",
        help="Also write result.mcap (scans by verdict, maps, paths, tf, the guard's decisions, "
        "rejected pairs; ROS 2 messages) for Foxglove, rviz2 and `ros2 bag play`.",
    ),
]
Live = Annotated[
    bool,
    typer.Option(
        "--live",
        help="Serve the same view on a Foxglove WebSocket while the run goes (needs the viz "
        "extra: pip install 'scanguard[viz]').",
    ),
]
LiveHost = Annotated[
    str, typer.Option("--host", metavar="ADDRESS", help="Address the live view binds.")
]
LivePort = Annotated[int, typer.Option("--port", help="Port of the live view.")]
MapInterval = Annotated[
    float,
    typer.Option(
        "--map-interval",
        metavar="SECONDS",
        help="Seconds of log time between two map frames of --mcap/--live (and at the end).",
    ),
]

OverwriteRecording = Annotated[
    bool,
    typer.Option(
        "--overwrite",
        help="Replace an existing recording at --output that scanguard did not write, and an "
        "existing picture at --preview.",
    ),
]
