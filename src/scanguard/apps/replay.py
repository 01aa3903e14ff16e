"""``scanguard run --realtime``: a recording played at its sensor's rate into the live node.

A robot gives the guard one scan at a time, at the laser's rate, and a scan that arrives while
the previous one is still being processed must wait or be dropped. `replay` makes a recording
behave the same way, with no ROS: a `scanguard.apps.node.GuardNode` (the worker, its queue of
``queue_size`` scans, the map thread, the same `scanguard.slam.loop.RunLoop` step as ``run``)
is offered each scan at its recorded spacing from the one before (divided by ``rate``;
`offer_times`) on the wall clock, by a
`RecordingTransport` that answers the node's odometry and laser-pose queries from the
recording. What the node could not keep up with is dropped and counted, as on the robot. The
kernels and the model are warmed up first (`scanguard.apps.loop_setup.warm_up`), as the live
node does before it subscribes.

The result is the node's: the main (guarded) instance alone, as ``run --no-compare`` (a
comparison instance would take CPU from the instance being measured), with the per-scan
latency (receive -> processed: the wait in the queue and the step), the step alone, and the
dropped scans. Its trajectory is scored like ``run``'s when the recording has Kümmerle
relations or a reference; relations that fall on a dropped scan are counted as unmatched,
because a live run has no pose there.
"""

from __future__ import annotations

import csv
import io
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.loop_setup import warm_up
from scanguard.apps.node import GuardNode, NodeOptions
from scanguard.errors import ConfigError
from scanguard.scan import ScanSequence
from scanguard.slam.config import RunConfig

logger = logging.getLogger(__name__)

#: Seconds the replay waits, after the last scan was offered, for the node to finish it.
DRAIN_TIMEOUT = 60.0
#: Columns of ``decisions.csv`` (the node's decision on each processed scan).
DECISION_COLUMNS = (
    "index",
    "stamp",
    "accepted",
    "fault_probability",
    "baseline_score",
    "reason",
    "motion_sources",
    "wheels_flagged",
    "latency_ms",
    "dropped",
)


class RecordingTransport:
    """The node's `scanguard.apps.node.Transport` for a recording (no ROS).

    Odometry is the recording's pose of the scan with that stamp (what tf would give at the
    scan's stamp); the laser sits at the recording's laser offset. Decisions are kept (for
    ``decisions.csv``); maps, paths and poses are not published anywhere, but the node still
    builds its maps on its map thread, so the replay costs what the live node costs.

    Args:
        stamps: The recording's scan stamps ``(N,)``.
        odometry: Robot odometry poses ``(N, 3)``, or None (a recording without).
        laser_offset: Pose of the laser in the robot frame.
    """

    def __init__(
        self,
        stamps: NDArray[np.float64],
        odometry: NDArray[np.float64] | None,
        laser_offset: NDArray[np.float64],
    ) -> None:
        self._index = first_index(stamps)
        self._odometry = odometry
        self._offset = np.asarray(laser_offset, dtype=np.float64).reshape(3)
        self.decisions: list[dict[str, Any]] = []

    def odometry(self, stamp: float, timeout: float) -> NDArray[np.float64] | None:
        """The recorded odometry pose of the scan with ``stamp`` (None without odometry)."""
        k = self._index.get(float(stamp))
        if self._odometry is None or k is None:
            return None
        return np.asarray(self._odometry[k], dtype=np.float64)

    def laser_offset(
        self, frame_id: str, stamp: float, timeout: float
    ) -> NDArray[np.float64] | None:
        """The recording's laser offset."""
        return self._offset.copy()

    def publish_decision(self, decision: Mapping[str, Any]) -> None:
        """Keep the decision (``decisions.csv``)."""
        self.decisions.append(dict(decision))

    def publish_pose(self, stamp: float, map_to_odom: NDArray[np.float64], odometry: bool) -> None:
        """Nothing listens to the pose of a replay."""

    def publish_map(self, grid: Any, stamp: float) -> None:
        """Nothing listens to the maps of a replay (they are built all the same)."""

    def publish_path(self, stamps: NDArray[np.float64], poses: NDArray[np.float64]) -> None:
        """Nothing listens to the path of a replay."""

    def publish_status(self, status: Mapping[str, Any]) -> None:
        """The status line is logged by the node."""


@dataclass
class ReplayResult:
    """What a replay at the sensor's rate measured.

    Attributes:
        name: The recording's name.
        rate: Playback speed (1: the sensor's rate).
        odometry: Whether the node had odometry.
        stats: The node's counts and latency (`scanguard.apps.node_stats.NodeStats.summary`).
        wall_seconds: Wall time from the first scan offered to the last one processed.
        log_seconds: Time span of the recording (its steps forward: `offer_times`).
        stamps: Stamps of the processed scans.
        trajectory: The guarded instance's robot poses at ``stamps`` ``(M, 3)``.
        errors: Error figures of the trajectory (relations, ATE), when the recording has a
            reference or relations.
        decisions: The node's decision on each processed scan.
        files: Files written.
    """

    name: str
    rate: float
    odometry: bool
    stats: dict[str, Any]
    wall_seconds: float
    log_seconds: float
    stamps: NDArray[np.float64]
    trajectory: NDArray[np.float64]
    errors: dict[str, Any] = field(default_factory=dict)
    decisions: list[dict[str, Any]] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)


def replay_options(odometry: bool, queue_size: int = 1) -> NodeOptions:
    """The node options of a replay: the node's defaults, odometry known beforehand."""
    if queue_size < 1:
        raise ConfigError(f"queue size must be 1 or more, not {queue_size}")
    return NodeOptions(use_odometry="on" if odometry else "off", queue_size=queue_size)


def replay(
    seq: ScanSequence,
    cfg: RunConfig,
    detector: Any,
    baseline: Any,
    odometry: NDArray[np.float64] | None,
    *,
    rate: float = 1.0,
    queue_size: int = 1,
    on_scan: Callable[[int, dict[str, Any]], None] | None = None,
) -> tuple[GuardNode, ReplayResult]:
    """Play ``seq`` at ``rate`` times its sensor's rate into a `GuardNode`; what it measured.

    Args:
        seq: The recording.
        cfg: Run settings (the comparisons are not run: the main instance alone).
        detector: The CNN fault detector.
        baseline: The classical detector the guard's policy may use, or None.
        odometry: Robot odometry poses ``(N, 3)`` (``run``'s `resolve_odometry`), or None.
        rate: Playback speed: 1 plays at the sensor's rate, 2 twice as fast.
        queue_size: Scans that may wait for the worker (the node's default: 1).
        on_scan: Called after each scan is offered, with its index and the node's counts.

    Returns:
        The node (to save its map) and the `ReplayResult` (not yet scored; see `score`).

    Raises:
        ConfigError: A rate that is not positive, or a node that stopped on an error.
    """
    if not (np.isfinite(rate) and rate > 0):
        raise ConfigError(f"the replay rate must be a positive number, not {rate}")
    stamps = np.asarray(seq.stamps, dtype=np.float64)
    cfg = cfg.model_copy(update={"compare": False})
    transport = RecordingTransport(stamps, odometry, seq.laser_offset)
    node = GuardNode(
        cfg, replay_options(odometry is not None, queue_size), detector, baseline, transport
    )
    # as the live node does before it subscribes: the kernels and the model load now, not
    # on the first scans (a robot's node is up before its laser starts)
    logger.info("warming up (kernels and model): %.1f s", warm_up(cfg, detector, baseline))
    node.start()
    at = offer_times(stamps, rate)
    t0 = time.monotonic()
    try:
        for k, scan in enumerate(seq.scans):
            wait = t0 + at[k] - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            if not node.running:
                break
            node.offer(scan, "laser")
            if on_scan is not None:
                on_scan(k, node.stats.summary())
        _drain(node)
    finally:
        node.stop()
    if node.error is not None:
        raise ConfigError(f"{seq.name}: the replay stopped: {node.error}") from node.error
    trajectory, _ = node.final()
    return node, ReplayResult(
        name=seq.name,
        rate=rate,
        odometry=node.odometry,
        stats=node.stats.summary(),
        wall_seconds=time.monotonic() - t0,
        log_seconds=float(at[-1] * rate) if len(at) else 0.0,
        stamps=np.asarray(node.stamps, dtype=np.float64),
        trajectory=np.asarray(trajectory, dtype=np.float64).reshape(-1, 3),
        decisions=transport.decisions,
    )


def offer_times(stamps: NDArray[np.float64], rate: float = 1.0) -> NDArray[np.float64]:
    """Seconds after the first scan at which each scan is offered.

    Consecutive scans keep their recorded spacing (divided by ``rate``). A stamp that steps
    back (a logger's artefact: the Intel log has 31 in its first 600 scans, up to 0.77 s) is
    offered right after the scan before it, and the scans after it keep their own spacing,
    rather than arriving all at once until the clock catches up with their stamps.
    """
    steps = np.diff(np.asarray(stamps, dtype=np.float64))
    return np.concatenate([[0.0], np.cumsum(np.maximum(steps, 0.0))]) / rate


def _drain(node: GuardNode) -> None:
    """Wait until the node has handled every scan offered (at most `DRAIN_TIMEOUT`)."""
    end = time.monotonic() + DRAIN_TIMEOUT
    while node.running and time.monotonic() < end:
        s = node.stats
        handled = s.processed + s.dropped + s.throttled + s.no_odometry + s.failed
        if handled >= s.received:
            return
        time.sleep(0.005)
    if node.running:
        logger.warning(
            "the node had not finished the last scans %.0f s after the end", DRAIN_TIMEOUT
        )


def score(res: ReplayResult, seq: ScanSequence, cfg: RunConfig) -> None:
    """The replay's errors: relations (all, and short ones) and the ATE on processed scans.

    Relations falling on a dropped scan are unmatched (the live run has no pose there).
    """
    from scanguard.io.relations import read_relations
    from scanguard.slam.metrics import trajectory_errors
    from scanguard.slam.relations import published_for, relation_errors

    if len(res.stamps) < 2:
        return
    if cfg.relations is not None:
        rel = read_relations(cfg.relations)
        tol = cfg.relation_tolerance
        full = relation_errors(res.stamps, res.trajectory, rel, tolerance=tol)
        short = relation_errors(
            res.stamps, res.trajectory, rel, max_dt=cfg.relations_short_dt, tolerance=tol
        )
        res.errors["relations"] = {
            "file": str(cfg.relations),
            "all": _relation_figures(full),
            "short": _relation_figures(short),
            "short_max_dt": cfg.relations_short_dt,
            "published": published_for(cfg.relations),
        }
    if seq.reference is not None:
        index = _processed_indices(np.asarray(seq.stamps, dtype=np.float64), res.stamps)
        ref = np.asarray(seq.reference, dtype=np.float64)[index]
        err = trajectory_errors(res.stamps, res.trajectory, ref)
        res.errors["ate_m"] = float(err.ate_rmse)
        res.errors["reference_kind"] = seq.reference_kind


def _relation_figures(e: Any) -> dict[str, Any]:
    return {
        "trans_mean_m": float(e.trans_mean),
        "trans_std_m": float(e.trans_std),
        "rot_mean_deg": float(e.rot_mean_deg),
        "matched": int(e.n_matched),
        "unmatched": int(e.n_unmatched),
        # of the unmatched: a stamp outside the recording (one cut by --max-scans)
        "outside": int(e.n_outside),
    }


def first_index(stamps: NDArray[np.float64]) -> dict[float, int]:
    """Stamp -> index of its scan (a repeated stamp: its first scan, as the relations do)."""
    index: dict[float, int] = {}
    for k, t in enumerate(np.asarray(stamps, dtype=np.float64).tolist()):
        index.setdefault(t, k)
    return index


def _processed_indices(all_stamps: NDArray[np.float64], done: NDArray[np.float64]) -> Any:
    """Index of each processed stamp among the recording's (its first scan with that stamp)."""
    first = first_index(all_stamps)
    return np.array([first[t] for t in done.tolist()], dtype=np.intp)


def decisions_csv(decisions: list[dict[str, Any]]) -> str:
    """The decisions as CSV text (`DECISION_COLUMNS`)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=DECISION_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for d in decisions:
        w.writerow(d)
    return buf.getvalue()


def run_realtime(
    seq: ScanSequence,
    detector: Any,
    out: Path,
    *,
    config: RunConfig,
    baseline: Any = None,
    rate: float = 1.0,
    on_scan: Callable[[int, dict[str, Any]], None] | None = None,
) -> ReplayResult:
    """``run --realtime``: replay ``seq`` at its sensor's rate, score it, write into ``out``.

    The odometry is ``run``'s (`scanguard.apps.run.resolve_odometry`: never the reference
    unless asked for); ``config.max_scans`` cuts the recording as in ``run``.
    """
    from scanguard.apps.run import resolve_odometry

    if config.max_scans is not None and len(seq) > config.max_scans:
        seq = seq.subsequence(slice(0, config.max_scans))
    odom, source = resolve_odometry(seq, config.odometry_noise, config.odometry, prior=config.prior)
    logger.info(
        "%s: %d scans played at %gx their rate into the live node (odometry %s)",
        seq.name,
        len(seq),
        rate,
        source,
    )
    node, res = replay(seq, config, detector, baseline, odom, rate=rate, on_scan=on_scan)
    score(res, seq, config)
    write_replay(node, res, out)
    return res


def write_replay(node: GuardNode, res: ReplayResult, out: Path) -> list[Path]:
    """Write the node's outputs, ``decisions.csv``, ``metrics.json`` and ``summary.md``.

    The node writes its map, trajectory, config and ``node.json``; every file goes through
    `scanguard.fsutil`.
    """
    from scanguard.apps.run_report import strict_json
    from scanguard.fsutil import atomic_write_text

    files = node.save(out)
    atomic_write_text(out / "decisions.csv", decisions_csv(res.decisions))
    atomic_write_text(out / "metrics.json", strict_json(replay_metrics(res)))
    atomic_write_text(out / "summary.md", "\n".join(replay_summary(res)) + "\n")
    files += [out / "decisions.csv", out / "metrics.json", out / "summary.md"]
    res.files = files
    return files


def replay_metrics(res: ReplayResult) -> dict[str, Any]:
    """``metrics.json`` of a replay."""
    return {
        "name": res.name,
        "realtime": {
            "rate": res.rate,
            "odometry": res.odometry,
            "wall_s": res.wall_seconds,
            "log_s": res.log_seconds,
            **res.stats,
        },
        "errors": res.errors,
    }


def replay_summary(res: ReplayResult) -> list[str]:
    """``summary.md`` of a replay: the live figures, then the errors."""
    s, lat, step = res.stats, res.stats["latency_ms"], res.stats["step_ms"]
    ms = format_ms

    lines = [
        f"# {res.name}: played at {res.rate:g}x the sensor's rate",
        "",
        f"The main (guarded) instance alone, as the live node runs it; odometry: "
        f"{'recorded' if res.odometry else 'none'}. {res.log_seconds:.1f} s of recording in "
        f"{res.wall_seconds:.1f} s of wall time.",
        "",
        "| scans received | processed | dropped (worker busy) | latency median / p99 / max (ms) "
        "| step median / p99 (ms) |",
        "|---|---|---|---|---|",
        f"| {s['received']} | {s['processed']} | {s['dropped']} | {ms(lat['median'])} / "
        f"{ms(lat['p99'])} / {ms(lat['max'])} | {ms(step['median'])} / {ms(step['p99'])} |",
    ]
    rel = res.errors.get("relations")
    if rel is not None:
        lines += [
            "",
            "| relations | matched | unmatched (outside the recording) | trans. err (m) "
            "| rot. err (deg) |",
            "|---|---|---|---|---|",
        ]
        for key, label in (("all", "all"), ("short", f"<= {rel['short_max_dt']:g} s")):
            e = rel[key]
            lines.append(
                f"| {label} | {e['matched']} | {e['unmatched']} ({e['outside']}) | "
                f"{e['trans_mean_m']:.4f} ± "
                f"{e['trans_std_m']:.4f} | {e['rot_mean_deg']:.2f} |"
            )
    if "ate_m" in res.errors:
        lines += ["", f"ATE (RMSE, aligned) on the processed scans: {res.errors['ate_m']:.4f} m"]
    return lines


def format_ms(v: float | None) -> str:
    """A latency figure (ms) for a table or a line; ``-`` before any scan."""
    return "-" if v is None else f"{v:.1f}"
