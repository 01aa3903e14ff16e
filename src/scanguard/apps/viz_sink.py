"""A run seen in Foxglove or rviz: `VizSink` turns the loop's steps into messages for outputs.

`VizSink` is a `scanguard.slam.loop.LoopObserver`; it encodes each message once
(`scanguard.apps.viz_messages`) and hands it to every `Output`: the MCAP file
(`scanguard.apps.mcap_sink.McapOutput`) and the Foxglove WebSocket server
(`scanguard.apps.live_sink.LiveOutput`). Channels, in the recording's time base:

* ``/scan`` (every scan), ``/scanguard/scan_accepted`` and ``/scanguard/scan_rejected`` (the
  scan by the guard's policy: accepted, or rejected / match failed; skipped scans in neither),
  ``sensor_msgs/LaserScan`` in frame ``laser``;
* ``/tf``: ``map -> base_link`` (the guarded instance's estimate), ``map -> <tag>/base_link``
  for every instance and ``map -> reference/base_link``; ``/tf_static``: ``base_link -> laser``;
  an instance's tag is its gate (`instance_tag`: ``unguarded``, ``cnn``, ``baseline``,
  ``oracle``), whatever the back end, so that one Foxglove layout opens every run;
* per instance ``/scanguard/<tag>/map`` (``nav_msgs/OccupancyGrid``) and
  ``/scanguard/<tag>/path`` (``nav_msgs/Path``) every ``map_interval`` seconds of log time
  (maps: of the unguarded and the guarded instance only, ``live_maps``; paths: at most
  `PATH_FRAME_POSES` poses, evenly thinned) and, at the end, the run's final map and whole
  trajectory of every instance (what its PGM and TUM files hold);
  ``/scanguard/reference/path`` at the end;
* ``/scanguard/decision`` (JSON): the guard's decision on every judged scan;
* ``/scanguard/rejected_pair`` (``sensor_msgs/CompressedImage``, PNG): the rendered pair of
  every scan the guard rejected.

During the run the maps are the sink's own grids: each instance's usable scans inserted at its
current estimate (a particle filter's best map is rebuilt only at the end, which would cost
the run more than a view may); the last frame is the instance's final map.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.viz_messages import (
    COMPRESSED_IMAGE,
    DECISION_SCHEMA,
    LASERSCAN,
    OCCUPANCY_GRID,
    PATH,
    TF_MESSAGE,
    ChannelSpec,
    Encoder,
    check_ros_stamps,
    json_bytes,
    stamp_ns,
)
from scanguard.geometry import compose
from scanguard.pairs.odometry import OdometryNoise, odometry_disagreement
from scanguard.scan import ScanSequence
from scanguard.slam.grid import GridConfig, OccupancyGrid, robot_to_sensor_increment
from scanguard.slam.loop import StepView

logger = logging.getLogger(__name__)

#: Default seconds of log time between two map (and path) frames.
MAP_INTERVAL = 5.0
SCAN_TOPIC = "/scan"
ACCEPTED_TOPIC = "/scanguard/scan_accepted"
REJECTED_TOPIC = "/scanguard/scan_rejected"
DECISION_TOPIC = "/scanguard/decision"
PAIR_TOPIC = "/scanguard/rejected_pair"
REFERENCE_PATH_TOPIC = "/scanguard/reference/path"


class Output(Protocol):
    """Where the view's messages go (an MCAP file, a WebSocket server)."""

    def add_channel(self, spec: ChannelSpec) -> None:
        """Declare a channel before its first message."""

    def write(self, topic: str, data: bytes, ns: int) -> None:
        """One message at log time ``ns`` (nanoseconds)."""


def instance_tag(gate: str) -> str:
    """Topic and frame name of an instance: its gate (``unguarded``, ``cnn``, ``baseline``...).

    The back end is not in the name, so that one Foxglove layout opens every run.
    """
    return "unguarded" if gate == "none" else gate


def map_topic(gate: str) -> str:
    """Map topic of the instance with gate ``gate`` (``none``, ``cnn``...)."""
    return f"/scanguard/{instance_tag(gate)}/map"


def path_topic(gate: str) -> str:
    """Path topic of the instance with gate ``gate``."""
    return f"/scanguard/{instance_tag(gate)}/path"


def _verdict(reason: str) -> str:
    if reason.startswith("rejected"):
        return "rejected"
    return {"match_failed": "failed", "skipped": "skipped"}.get(reason, "accepted")


#: Most poses of a path frame during the run (evenly thinned, first and newest kept): one
#: frame per map interval with every pose so far made a long run's view quadratic in time
#: and size; the frame at the end holds every pose.
PATH_FRAME_POSES = 4096


def thin_indices(n: int, most: int) -> NDArray[np.intp]:
    """At most ``most`` indices of ``range(n)``, evenly spaced, with the first and the last."""
    if n <= most:
        return np.arange(n, dtype=np.intp)
    return np.unique(np.linspace(0, n - 1, most).round().astype(np.intp))


class _Track:
    """Rows appended one at a time to a buffer that doubles: O(1) each, all rows in O(1)."""

    def __init__(self, width: int) -> None:
        self._buf = np.empty((256, width), dtype=np.float64)
        self._n = 0

    def append(self, row: NDArray[np.float64]) -> None:
        if self._n == len(self._buf):
            self._buf = np.concatenate([self._buf, np.empty_like(self._buf)])
        self._buf[self._n] = np.asarray(row, dtype=np.float64).reshape(-1)
        self._n += 1

    def rows(self) -> NDArray[np.float64]:
        """The rows so far (a view: valid until the next `append`)."""
        return self._buf[: self._n]


class VizSink:
    """The loop observer that writes a run's view to outputs (see the module docstring).

    Args:
        outputs: Where the messages go.
        map_interval: Seconds of log time between map and path frames (0: every scan).
        grid: Settings of the maps drawn during the run.
        odometry_noise: Noise model of the odometry disagreement in the decisions.
        guarded: Gate of the instance whose estimate is ``base_link`` (the guard's policy).
        live_maps: Gates whose maps are drawn during the run (the others: the final map only;
            each drawn map costs one ray-traced scan per scan).
    """

    def __init__(
        self,
        outputs: Sequence[Output],
        *,
        map_interval: float = MAP_INTERVAL,
        grid: GridConfig | None = None,
        odometry_noise: OdometryNoise | None = None,
        guarded: str = "cnn",
        live_maps: Sequence[str] = ("none", "cnn"),
    ) -> None:
        from scanguard.detect.render import RenderStyle

        self.outputs = list(outputs)
        self.map_interval = float(map_interval)
        self.grid_config = grid or GridConfig()
        self.noise = odometry_noise or OdometryNoise()
        self.guarded = guarded
        self.live_maps = frozenset(live_maps)
        self.style = RenderStyle()
        self.enc = Encoder()
        self.counts: dict[str, int] = {}
        self._names: dict[str, str] = {}
        self._grids: dict[str, OccupancyGrid] = {}
        self._poses: dict[str, _Track] = {}
        self._stamps = _Track(1)
        self._last_map = -np.inf
        self._seq: ScanSequence | None = None

    # --- outputs ----------------------------------------------------------------------------

    def _channel(self, spec: ChannelSpec) -> None:
        self.counts[spec.topic] = 0
        for out in self.outputs:
            out.add_channel(spec)

    def _write(self, topic: str, data: bytes, ns: int) -> None:
        self.counts[topic] += 1
        for out in self.outputs:
            out.write(topic, data, ns)

    # --- LoopObserver -----------------------------------------------------------------------

    def begin(self, seq: ScanSequence, names: Mapping[str, str]) -> None:
        """Declare the channels; write ``/tf_static`` (``base_link -> laser``).

        Raises:
            InputError: The stamps cannot be ROS times (`check_ros_stamps`).
        """
        source = str(seq.metadata.get("path") or seq.metadata.get("source") or seq.name)
        check_ros_stamps(seq.stamps, source)
        enc = self.enc
        self._seq, self._names = seq, dict(names)
        for topic in (SCAN_TOPIC, ACCEPTED_TOPIC, REJECTED_TOPIC):
            self._channel(enc.ros_channel(topic, LASERSCAN))
        self._channel(enc.ros_channel("/tf", TF_MESSAGE))
        self._channel(enc.ros_channel("/tf_static", TF_MESSAGE))
        self._channel(enc.json_channel(DECISION_TOPIC, "scanguard.Decision", DECISION_SCHEMA))
        self._channel(enc.ros_channel(PAIR_TOPIC, COMPRESSED_IMAGE))
        for g in names:
            self._channel(enc.ros_channel(map_topic(g), OCCUPANCY_GRID))
            self._channel(enc.ros_channel(path_topic(g), PATH))
            self._poses[g] = _Track(3)
        if seq.reference is not None:
            self._channel(enc.ros_channel(REFERENCE_PATH_TOPIC, PATH))
        ns = stamp_ns(float(seq.stamps[0])) if len(seq) else 0
        offset = np.asarray(seq.laser_offset, dtype=np.float64)
        self._write("/tf_static", enc.tf(ns, [("base_link", "laser", offset)]), ns)

    def step(self, view: StepView) -> None:
        """The scan, its split by verdict, tf, the decision, a rejected pair's image, maps."""
        enc, scan, step = self.enc, view.scan, view.step
        ns = stamp_ns(scan.stamp)
        data = enc.laser_scan(scan, ns, "laser")
        self._write(SCAN_TOPIC, data, ns)
        verdict = _verdict(step.reason)
        if verdict == "accepted":
            self._write(ACCEPTED_TOPIC, data, ns)
        elif verdict in ("rejected", "failed"):
            self._write(REJECTED_TOPIC, data, ns)
        self._write("/tf", enc.tf(ns, self._transforms(view)), ns)
        if step.reason not in ("first", "skipped"):
            self._write(DECISION_TOPIC, json_bytes(self._decision(view, verdict)), ns)
        if verdict == "rejected" and view.pair.previous is not None and step.match is not None:
            image = self._pair_image(view)
            self._write(PAIR_TOPIC, enc.png_image(image, ns, "laser"), ns)
        self._stamps.append(np.array([scan.stamp]))
        self._grow_maps(view)
        if scan.stamp - self._last_map >= self.map_interval:
            self._last_map = scan.stamp
            stamps = self._stamps.rows()[:, 0]
            keep = thin_indices(len(stamps), PATH_FRAME_POSES)
            for g in self._names:
                if g in self._grids:
                    self._write(map_topic(g), enc.occupancy_grid(self._grids[g], ns), ns)
                poses = self._poses[g].rows()
                self._write(path_topic(g), enc.path(stamps[keep], poses[keep], ns), ns)

    def end(
        self, trajectories: Mapping[str, NDArray[np.float64]], grids: Mapping[str, Any]
    ) -> None:
        """The final map and path of every instance, and the reference path."""
        seq = self._seq
        if seq is None or not len(seq):
            return
        stamps = np.asarray(seq.stamps, dtype=np.float64)
        ns = stamp_ns(float(stamps[-1]))
        for g in self._names:
            self._write(map_topic(g), self.enc.occupancy_grid(grids[g], ns), ns)
            self._write(path_topic(g), self.enc.path(stamps, trajectories[g], ns), ns)
        if seq.reference is not None:
            ref = np.asarray(seq.reference, dtype=np.float64)
            self._write(REFERENCE_PATH_TOPIC, self.enc.path(stamps, ref, ns), ns)
        logger.info("view: %d messages on %d channels", sum(self.counts.values()), len(self.counts))

    # --- pieces -----------------------------------------------------------------------------

    def _transforms(self, view: StepView) -> list[tuple[str, str, NDArray[np.float64]]]:
        poses = {g: np.asarray(p, dtype=np.float64).reshape(3) for g, p in view.poses.items()}
        out = [("map", "base_link", poses[self.guarded])] if self.guarded in poses else []
        out += [("map", f"{instance_tag(g)}/base_link", p) for g, p in poses.items()]
        seq = self._seq
        if seq is not None and seq.reference is not None:
            ref = np.asarray(seq.reference[view.step.index], dtype=np.float64)
            out.append(("map", "reference/base_link", ref))
        for g, p in poses.items():
            self._poses[g].append(p)
        return out

    def _decision(self, view: StepView, verdict: str) -> dict[str, Any]:
        step, pair = view.step, view.pair
        v = step.verdict
        trans_z = rot_z = float("nan")
        if pair.odometry_increment is not None and pair.match_pose is not None:
            seq = self._seq
            offset = np.zeros(3) if seq is None else seq.laser_offset
            odo = robot_to_sensor_increment(pair.odometry_increment, offset)
            d = odometry_disagreement(pair.match_pose[None], odo[None], self.noise)
            trans_z, rot_z = float(d["odom_trans_z"][0]), float(d["odom_rot_z"][0])
        return {
            "index": int(step.index),
            "stamp": float(step.stamp),
            "fault_probability": None if v is None else v.fault_probability,
            "baseline_score": None if v is None else v.baseline_score,
            "accepted": bool(step.accepted),
            "verdict": verdict,
            "reason": step.reason,
            "reference_label": None if v is None else v.reference_label,
            "odom_trans_z": trans_z,
            "odom_rot_z": rot_z,
            "motion_sources": None if step.motion is None else step.motion.sources,
            "wheels_flagged": None if step.motion is None else bool(step.motion.wheels_flagged),
            "instances": {self._names[g]: bool(u) for g, u in view.usable.items()},
        }

    def _pair_image(self, view: StepView) -> NDArray[np.uint8]:
        from scanguard.detect.render import render_pair

        prev = view.pair.previous
        assert prev is not None  # checked by the caller
        pose = np.asarray(view.step.match.pose, dtype=np.float64)
        return render_pair(prev.points, view.pair.current.points, pose, self.style)

    def _grow_maps(self, view: StepView) -> None:
        """Insert the scan into the view's map of every instance that used it."""
        seq = self._seq
        offset = np.zeros(3) if seq is None else np.asarray(seq.laser_offset, dtype=np.float64)
        for g, pose in view.poses.items():
            if g not in self.live_maps:
                continue
            grid = self._grids.get(g)
            if grid is None:
                p = np.asarray(pose, dtype=np.float64).reshape(3)
                origin = (float(p[0]) - 10.0, float(p[1]) - 10.0)
                grid = self._grids[g] = OccupancyGrid(self.grid_config, origin=origin)
            if view.usable[g] and view.wanted[g]:
                grid.insert(view.scan, compose(np.asarray(pose, dtype=np.float64), offset))


@dataclass(frozen=True)
class ViewOptions:
    """Where a run's view goes (``--mcap``, ``--live``, ``--host``, ``--port``, ``--map-interval``).

    Attributes:
        mcap: Write ``result.mcap`` into the run's output folder.
        live: Serve the view on a Foxglove WebSocket while the run goes.
        host: Address the live view binds.
        port: Port of the live view (0: any free port).
        map_interval: Seconds of log time between map and path frames.
    """

    mcap: bool = False
    live: bool = False
    host: str = "127.0.0.1"
    port: int = 8765
    map_interval: float = MAP_INTERVAL

    @property
    def wanted(self) -> bool:
        """Some view was asked for."""
        return self.mcap or self.live

    def check(self) -> None:
        """Fail now (before any long work) when the live view cannot be served.

        Raises:
            ConfigError: ``--live`` without the ``viz`` extra.
        """
        if self.live:
            from scanguard.apps.live_sink import import_foxglove

            import_foxglove()


@contextlib.contextmanager
def open_view(
    options: ViewOptions,
    out_dir: str | Path,
    *,
    grid: GridConfig | None = None,
    odometry_noise: OdometryNoise | None = None,
) -> Iterator[VizSink | None]:
    """The run's view sink for ``options`` (None when no view was asked for).

    Args:
        options: What to write or serve.
        out_dir: The run's output folder (its temporary folder inside a `ResultDir`).
        grid: Settings of the maps drawn during the run.
        odometry_noise: Noise model of the odometry disagreement.

    Yields:
        The sink to pass to `scanguard.apps.run.run_recording` (``observer``); on leaving, the
        MCAP file is finished and the live server stopped (also on an error or Ctrl-C, when
        no MCAP file is left behind).
    """
    if not options.wanted:
        yield None
        return
    from scanguard.apps.live_sink import LiveOutput
    from scanguard.apps.mcap_sink import MCAP_NAME, McapOutput

    with contextlib.ExitStack() as stack:
        outputs: list[Output] = []
        if options.live:
            outputs.append(stack.enter_context(LiveOutput(options.host, options.port)))
        if options.mcap:
            outputs.append(stack.enter_context(McapOutput(Path(out_dir) / MCAP_NAME)))
        yield VizSink(
            outputs,
            map_interval=options.map_interval,
            grid=grid,
            odometry_noise=odometry_noise,
        )
