"""A peer measured side by side: Debian's MRPT 2.5.8 apps against scanguard, same logs, same metric.

Usage::

    python benchmarks/peer_mrpt.py [--logs fr079 intel aces] [--ours gmapping graph]
                                   [--peers icp-slam icp-slam-grid rbpf-grid rbpf-points]
                                   [--out runs/peer_mrpt] [--seed 0] [--force]

For each shared Freiburg log (``<data>/<log>.clf.gz`` with ``<log>.relations``):

* the peer: MRPT's ``icp-slam`` (shipped ``icp-slam_demo_classic.ini``, scan to point map;
  ``icp-slam_demo_classic_gridmatch.ini``, scan to grid) and ``rbpf-slam`` (shipped
  ``gridmapping_RBPF_grid_ICPbased_malaga.ini``: occupancy grid, ICP-based proposal against
  the grid; ``gridmapping_RBPF_ICPbased_intel.ini``: ICP proposal against a point map), each
  unchanged except the input, the output folder, ``RANDOM_SEED`` (``--seed``, default 0) and
  the app's output switches (no window, 3D scenes, map images or periodic logs; they do not
  touch the estimate). ``graph-slam`` optimises a given pose graph (.graph/.g2o) and has no
  front end for a laser log, so it does not apply.
  The apps are installed with apt when missing (the command is printed).
* the input: MRPT 2.5.8's ``carmen2rawlog`` gives every observation of these logs the same
  timestamp (icp-slam then ignores the odometry) and writes only the observation layout that
  rbpf-slam cannot read, so a small converter (``peer_mrpt/scans2rawlog.cpp``, built here
  against ``libmrpt-obs-dev``) writes the rawlogs from scanguard's reader: the same scans,
  stamps, raw odometry (FLASER odometry fields) and beam geometry that scanguard reads.
* their output: ``log_estimated_path.txt`` (robot pose after each rawlog entry) becomes a TUM
  trajectory at the scan stamps (rbpf-slam: the mean of its particles after each scan, its
  online estimate). Where the app left its estimate unchanged at a scan, the pose is the last
  estimate composed with the raw odometry since (what a filter reports between its updates).
* ours, in the same run: ``scanguard run LOG --no-compare --baseline none`` (GMapping guarded
  by the shipped CNN; the main result ``trajectory.tum``) and the same with ``--backend graph``.
* the metric: `scanguard.slam.relations.relation_errors`, every relation, nearest scan stamp
  within 1 ms; mean absolute translational error. x real time = log duration / wall time of
  the app (or of the whole ``scanguard run`` process), on this machine, in this run.

Resumable: a run whose ``result.json`` exists is not run again (``--force`` reruns). Outputs go
to ``--out`` (default ``runs/peer_mrpt``, ignored by git); the table is printed and, with
``--table``, written as Markdown.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from scanguard.fsutil import atomic_write_text
from scanguard.geometry import compose, relative
from scanguard.io import read_sequence
from scanguard.io.relations import read_relations
from scanguard.io.tum import read_tum, write_tum
from scanguard.scan import ScanSequence
from scanguard.slam.relations import relation_errors

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent / "peer_mrpt"
DATA = Path("/work/shared/data/benchmark")
MRPT_CONFIGS = Path("/usr/share/mrpt/config_files")
APT_PACKAGES = ["mrpt-apps", "mrpt-common", "libmrpt-obs-dev", "libmrpt-io-dev", "g++"]
TOLERANCE = 1e-3  # s: a relation stamp takes the nearest scan stamp within 1 ms


@dataclass(frozen=True)
class Peer:
    """One MRPT app with its shipped config."""

    name: str
    app: str
    config: str
    layout: str  # "obs": observation-only rawlog; "sf": action / sensory-frame pairs
    matcher: str
    backend: str


PEERS = {
    "icp-slam": Peer(
        "icp-slam",
        "icp-slam",
        "icp-slam/icp-slam_demo_classic.ini",
        "sf",
        "MRPT ICP (classic, scan to point map)",
        "MRPT icp-slam (icp-slam_demo_classic.ini)",
    ),
    "icp-slam-grid": Peer(
        "icp-slam-grid",
        "icp-slam",
        "icp-slam/icp-slam_demo_classic_gridmatch.ini",
        "sf",
        "MRPT ICP (classic, scan to grid)",
        "MRPT icp-slam (icp-slam_demo_classic_gridmatch.ini)",
    ),
    "rbpf-grid": Peer(
        "rbpf-grid",
        "rbpf-slam",
        "rbpf-slam/gridmapping_RBPF_grid_ICPbased_malaga.ini",
        "sf",
        "MRPT ICP (proposal, scan to grid)",
        "MRPT rbpf-slam, 10 particles (gridmapping_RBPF_grid_ICPbased_malaga.ini)",
    ),
    "rbpf-points": Peer(
        "rbpf-points",
        "rbpf-slam",
        "rbpf-slam/gridmapping_RBPF_ICPbased_intel.ini",
        "sf",
        "MRPT ICP (proposal, scan to point map)",
        "MRPT rbpf-slam, 10 particles (gridmapping_RBPF_ICPbased_intel.ini)",
    ),
}

# Output switches of the apps (windows, 3D scenes, images, periodic logs): not the estimate.
OUTPUT_SWITCHES = {
    "LOG_FREQUENCY": "0",
    "SAVE_3D_SCENE": "0",
    "SAVE_MAP_IMAGES": "0",
    "SAVE_POSE_LOG": "0",
    "SHOW_PROGRESS_3D_REAL_TIME": "0",
    "SHOW_PROGRESS_IN_WINDOW": "0",
    "SHOW_LASER_SCANS_3D": "false",
    "CAMERA_3DSCENE_FOLLOWS_ROBOT": "0",
    "verbosity_level": "INFO",
}

OURS = {
    "gmapping": (
        [],
        "icp-paper (guard) + GMapping's scan matcher",
        "scanguard gmapping (30 particles)",
        "CNN",
    ),
    "graph": (
        ["--backend", "graph"],
        "icp-paper (guard) + correlative/plicp",
        "scanguard graph (default closure judge)",
        "CNN",
    ),
}


def say(text: str) -> None:
    """Progress line, flushed at once (the runs take minutes)."""
    print(f"[{time.strftime('%H:%M:%S')}] {text}", flush=True)


def run_shell(cmd: list[str]) -> None:
    """Run a setup command, printed first."""
    say("$ " + shlex.join(cmd))
    subprocess.run(cmd, check=True)


def ensure_mrpt() -> None:
    """Install the peer (Debian's MRPT 2.5.8 apps, configs and headers) when missing."""
    have = all(shutil.which(a) for a in ("icp-slam", "rbpf-slam", "g++"))
    have = have and (MRPT_CONFIGS / PEERS["icp-slam"].config).exists()
    have = have and Path("/usr/include/mrpt/obs/include/mrpt/obs/CSensoryFrame.h").exists()
    if have:
        return
    sudo = [] if os.geteuid() == 0 else ["sudo"]
    run_shell([*sudo, "apt-get", "update"])
    run_shell([*sudo, "apt-get", "install", "-y", *APT_PACKAGES])


def build_converter(out: Path) -> Path:
    """Compile ``scans2rawlog`` against MRPT (once)."""
    exe = out / "bin" / "scans2rawlog"
    source = HERE / "scans2rawlog.cpp"
    if exe.exists() and exe.stat().st_mtime >= source.stat().st_mtime:
        return exe
    exe.parent.mkdir(parents=True, exist_ok=True)
    includes = [f"-I{d}" for d in sorted(Path("/usr/include/mrpt").glob("*/include"))]
    libs = ["obs", "io", "serialization", "poses", "system", "core", "rtti", "math"]
    run_shell(
        ["g++", "-O2", "-std=c++17", *includes, str(source), "-o", str(exe)]
        + [f"-lmrpt-{lib}" for lib in libs]
    )
    return exe


def write_scans(seq: ScanSequence, path: Path) -> None:
    """The converter's input: stamp, raw odometry, max range, aperture, ranges per scan."""
    if seq.odometry is None:
        raise SystemExit(f"error: {seq.name}: no odometry in the log")
    lines = []
    for scan, odo in zip(seq.scans, seq.odometry, strict=True):
        n = len(scan.ranges)
        aperture = abs(scan.angle_increment) * (n - 1)
        # MRPT spreads the beams symmetrically over [-aperture/2, aperture/2], right to left.
        if abs(scan.angle_min + aperture / 2) > 1e-6 or scan.angle_increment <= 0:
            raise SystemExit(f"error: {seq.name}: scans are not symmetric right-to-left")
        ranges = " ".join(f"{r:.3f}" if math.isfinite(r) else "0" for r in scan.ranges.tolist())
        lines.append(
            f"{scan.stamp:.6f} {odo[0]:.6f} {odo[1]:.6f} {odo[2]:.6f} "
            f"{scan.range_max:.3f} {aperture:.9f} {n} {ranges}"
        )
    atomic_write_text(path, "\n".join(lines) + "\n")


def peer_ini(peer: Peer, rawlog: Path, out_dir: Path, dest: Path, seed: int) -> None:
    """The shipped config with the input, output folder, output switches and seed set."""
    text = (MRPT_CONFIGS / peer.config).read_text()
    sets = {
        "rawlog_file": str(rawlog),
        "logOutput_dir": str(out_dir),
        "RANDOM_SEED": str(seed),  # rbpf-slam: one fixed seed, so a rerun gives the same
        **OUTPUT_SWITCHES,
    }
    for key, value in sets.items():
        text, found = re.subn(rf"(?m)^(\s*){key}\s*=.*$", rf"\g<1>{key}={value}", text)
        if not found and key in ("RANDOM_SEED", "rawlog_file", "logOutput_dir"):
            text = text.replace("[MappingApplication]", f"[MappingApplication]\n{key}={value}", 1)
    atomic_write_text(dest, text)


def _rows(path: Path) -> NDArray[np.float64]:
    rows = [
        [float(v) for v in line.split()]
        for line in path.read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("%")
    ]
    return np.asarray(rows, dtype=np.float64)


def mrpt_path_to_poses(
    estimated: Path, odometry: Path, layout: str, n_scans: int
) -> NDArray[np.float64]:
    """Robot poses at the scans from an app's ``log_estimated_path.txt``.

    Rows are ``step x y [z] yaw ...``, one per rawlog entry: observation layout, entries
    ``2k`` (odometry) and ``2k + 1`` (scan k); sensory-frame layout, entry k is scan k.
    Where the estimate did not move since the previous scan, the pose is the last estimate
    composed with the odometry since that estimate (the filter's pose between updates).
    """
    est, odo = _rows(estimated), _rows(odometry)
    # icp-slam writes ``step x y yaw``, rbpf-slam ``step x y z yaw pitch roll [stamp]``
    est_xyt = est[:, [1, 2, 3 if est.shape[1] == 4 else 4]]
    odo_xyt = odo[:, [1, 2, 3 if odo.shape[1] == 4 else 4]]
    idx = np.arange(n_scans) * 2 + 1 if layout == "obs" else np.arange(n_scans)
    if len(est_xyt) < idx[-1] + 1:
        raise SystemExit(f"error: {estimated}: {len(est_xyt)} steps, expected {idx[-1] + 1}")
    est_xyt, odo_xyt = est_xyt[idx], odo_xyt[idx]
    poses = est_xyt.copy()
    anchor = 0
    for k in range(1, n_scans):
        if np.array_equal(est_xyt[k], est_xyt[k - 1]):
            poses[k] = compose(est_xyt[anchor], relative(odo_xyt[anchor], odo_xyt[k]))
        else:
            anchor = k
    return poses


def timed(cmd: list[str], log: Path, progress: Callable[[], str]) -> float:
    """Run ``cmd`` with its output in ``log``; print progress every 30 s; wall seconds."""
    say("$ " + shlex.join(cmd))
    start = time.perf_counter()
    with log.open("w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        while True:
            try:
                proc.wait(timeout=30)
                break
            except subprocess.TimeoutExpired:
                say(f"  ... {time.perf_counter() - start:.0f} s {progress()}")
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        tail = log.read_text(errors="replace")[-2000:]
        raise SystemExit(f"error: {cmd[0]} exited {proc.returncode}; end of {log}:\n{tail}")
    return wall


def _lines(path: Path) -> int:
    try:
        with path.open("rb") as fh:
            return sum(1 for _ in fh)
    except OSError:
        return 0


def run_peer(
    peer: Peer, log: str, seq: ScanSequence, work: Path, exe: Path, force: bool, seed: int
) -> dict:
    """Run one MRPT app on one log (resumable); its poses written as TUM."""
    run_dir = work / log / peer.name
    result = run_dir / "result.json"
    if result.exists() and not force:
        say(f"{log} {peer.name}: done before, reusing {run_dir}")
        return dict(json.loads(result.read_text()))
    run_dir.mkdir(parents=True, exist_ok=True)
    rawlog = work / log / f"{log}.{peer.layout}.rawlog"
    if not rawlog.exists():
        scans = work / log / "scans.txt"
        if not scans.exists():
            write_scans(seq, scans)
        run_shell([str(exe), str(scans), str(rawlog), peer.layout])
    ini = run_dir / "config.ini"
    app_out = run_dir / "mrpt_out"
    peer_ini(peer, rawlog, app_out, ini, seed)
    entries = len(seq.scans) * (2 if peer.layout == "obs" else 1)
    path_file = app_out / "log_estimated_path.txt"
    wall = timed(
        [peer.app, str(ini), str(rawlog)],
        run_dir / "app.log",
        lambda: f"{_lines(path_file)}/{entries} rawlog entries",
    )
    poses = mrpt_path_to_poses(
        path_file, app_out / "log_odometry_path.txt", peer.layout, len(seq.scans)
    )
    stamps = np.array([s.stamp for s in seq.scans])
    write_tum(run_dir / "trajectory.tum", stamps, poses)
    info = {"wall_s": wall, "trajectory": str(run_dir / "trajectory.tum")}
    atomic_write_text(result, json.dumps(info))
    return info


def run_ours(name: str, log: str, path: Path, work: Path, force: bool) -> dict:
    """``scanguard run`` on one log (resumable); wall time of the whole process."""
    run_dir = work / log / f"scanguard-{name}"
    result = run_dir / "result.json"
    if result.exists() and not force:
        say(f"{log} scanguard {name}: done before, reusing {run_dir}")
        return dict(json.loads(result.read_text()))
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    scanguard = Path(sys.executable).with_name("scanguard")
    cmd = [
        str(scanguard) if scanguard.exists() else "scanguard",
        "run",
        str(path),
        "-o",
        str(run_dir / "out"),
        "--no-compare",
        "--baseline",
        "none",
        "--overwrite",
        *OURS[name][0],
    ]
    wall = timed(cmd, work / log / f"scanguard-{name}.log", lambda: "")
    traj = run_dir / "out" / "trajectory.tum"
    info = {"wall_s": wall, "trajectory": str(traj)}
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(result, json.dumps(info))
    return info


def score(traj: Path, relations: Path) -> tuple[str, float]:
    """(relations used, mean absolute translational error) with our metric."""
    stamps, poses = read_tum(traj)
    err = relation_errors(stamps, poses, read_relations(relations), tolerance=TOLERANCE)
    return err.used_text(), err.trans_mean


def table_for(log: str, rows: list[list[str]]) -> str:
    """One Markdown table."""
    head = [
        "log",
        "system",
        "odometry",
        "matcher",
        "back end",
        "gate",
        "relations used",
        "trans. error (m)",
        "x real time",
    ]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join([log, *r]) + " |" for r in rows]
    return "\n".join(out)


def bench_log(log: str, args: argparse.Namespace, exe: Path | None) -> str:
    """All systems on one log; its table."""
    path = args.data / f"{log}.clf.gz"
    relations = args.data / f"{log}.relations"
    work = args.out
    say(f"{log}: reading {path}")
    seq = read_sequence(path)
    stamps = np.array([s.stamp for s in seq.scans])
    duration = float(stamps[-1] - stamps[0])
    say(f"{log}: {len(seq.scans)} scans, {duration:.0f} s of log")
    rows: list[list[str]] = []
    odo = "raw wheel (FLASER)"
    if seq.odometry is not None:
        raw = work / log / "odometry.tum"
        raw.parent.mkdir(parents=True, exist_ok=True)
        write_tum(raw, stamps, seq.odometry)
        used, err = score(raw, relations)
        rows.append(["raw odometry", odo, "-", "-", "-", used, f"{err:.3f}", "-"])
    for name in args.peers:
        peer = PEERS[name]
        assert exe is not None
        info = run_peer(peer, log, seq, work, exe, args.force, args.seed)
        used, err = score(Path(info["trajectory"]), relations)
        speed = duration / info["wall_s"]
        say(f"{log} {name}: {err:.3f} m, {speed:.0f}x real time")
        rows.append(
            [peer.name, odo, peer.matcher, peer.backend, "-", used, f"{err:.3f}", f"{speed:.0f}"]
        )
    for name in args.ours:
        info = run_ours(name, log, path, work, args.force)
        used, err = score(Path(info["trajectory"]), relations)
        speed = duration / info["wall_s"]
        say(f"{log} scanguard {name}: {err:.3f} m, {speed:.1f}x real time")
        _, matcher, backend, gate = OURS[name]
        rows.append(
            [f"scanguard ({name})", odo, matcher, backend, gate, used, f"{err:.3f}", f"{speed:.1f}"]
        )
    return table_for(log, rows)


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", nargs="+", default=["fr079", "intel", "aces"])
    ap.add_argument("--peers", nargs="*", default=list(PEERS), choices=sorted(PEERS))
    ap.add_argument("--ours", nargs="*", default=["gmapping", "graph"], choices=sorted(OURS))
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "peer_mrpt")
    ap.add_argument("--table", type=Path, default=None, help="Also write the tables here.")
    ap.add_argument("--force", action="store_true", help="Rerun runs that are done.")
    ap.add_argument("--seed", type=int, default=0, help="rbpf-slam's RANDOM_SEED.")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    exe = None
    if args.peers:
        ensure_mrpt()
        exe = build_converter(args.out)
    load = os.getloadavg()[0]
    tables = []
    for log in args.logs:
        tables.append(bench_log(log, args, exe))
        print("\n" + tables[-1] + "\n", flush=True)
    text = f"load average at the end: {os.getloadavg()[0]:.1f} (start {load:.1f})\n\n"
    text += "\n\n".join(tables) + "\n"
    print(text)
    if args.table is not None:
        atomic_write_text(args.table, text)


if __name__ == "__main__":
    main()
