"""The `gmapping` back end: a Rao-Blackwellised particle filter.

After Grisetti, Stachniss and Burgard (IEEE T-RO 2007) and OpenSLAM's ``GridSlamProcessor``
(``gridfastslam/``).

Per scan (``processScan``):

1. every particle moves by the odometry step through the motion model (`motion`);
2. only when the robot has travelled ``linearUpdate``, turned ``angularUpdate`` or waited
   ``temporalUpdate`` since the last processed scan (or on the first scan), the scan is
   processed:

   a. each particle scan-matches against its own map (hill climbing on GMapping's score);
      a match scoring at or below ``minimumScore`` keeps the odometry pose;
   b. the improved proposal: the likelihood times the motion prior is evaluated on a small
      grid around the mode, a Gaussian is fitted to it, the particle is drawn from that
      Gaussian and its weight multiplied by the grid's total (``proposal="mode"``: the
      particle is put at the mode and weighted by the likelihood there, as OpenSLAM does);
   c. weights are normalised with the ``ogain`` smoothing; when Neff falls below
      ``resampleThreshold * particles`` the particles are resampled (systematic resampling),
      maps shared, weights reset;
   d. the scan is registered into every particle's map (copy-on-write patches, `maps`).

A scan the guard rejects (``usable=False``) is never matched nor registered: the particles
have moved by the motion model only, and the next usable scan is processed in its place (the
travelled-distance counters are not reset).

Without odometry (``odometry=None``) the motion prior is zero motion and every scan is
processed (no travelled distance to trigger on). A non-finite odometry pose is treated as
missing for that scan (zero motion), with one warning per run.

The reported trajectory is the best particle's (highest accumulated log-likelihood): its pose
at each processed scan, and in between that pose moved by the odometry since, which is what
``slam_gmapping`` publishes. The map is rebuilt from that trajectory and the processed scans,
as ``slam_gmapping``'s ``updateMap`` does.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import scanguard.slam.gmapping._kernels as kern
from scanguard.errors import ConfigError
from scanguard.geometry import as_pose, compose, relative, wrap_angle
from scanguard.scan import LaserScan
from scanguard.slam.backend import checked_odometry, finite_odometry
from scanguard.slam.gmapping.config import GMappingConfig
from scanguard.slam.gmapping.maps import PatchMaps
from scanguard.slam.gmapping.motion import motion_sigma, sample_motion
from scanguard.slam.rows import Rows

logger = logging.getLogger(__name__)

#: Floor of the proposal covariance (m^2, m^2, rad^2): a grid whose likelihood sits on one
#: sample would otherwise give a singular Gaussian.
_PROPOSAL_JITTER = np.array([1e-6, 1e-6, 1e-7])
#: Floor of the motion prior's standard deviations (m, m, rad): a zero odometry step must not
#: make the prior a Dirac.
_PRIOR_FLOOR = np.array([0.01, 0.01, 0.005])
#: A one-point sample grid: the likelihood at the pose itself.
_NO_OFFSET = np.zeros((1, 3))


def normalized_weights(log_weights: ArrayLike, ogain: float) -> NDArray[np.float64]:
    """GMapping's ``normalize``: ``w ~ exp((l - max l) / (ogain * P))``, summing to one."""
    lw = np.asarray(log_weights, dtype=np.float64)
    gain = 1.0 / (ogain * len(lw))
    w = np.exp(gain * (lw - lw.max()))
    return np.asarray(w / w.sum())


def effective_sample_size(weights: ArrayLike) -> float:
    """Neff = 1 / sum(w^2) of normalised weights."""
    w = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(w * w))


def systematic_resample(weights: ArrayLike, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices drawn by systematic (low-variance) resampling, as OpenSLAM's ``resampleIndexes``."""
    w = np.asarray(weights, dtype=np.float64)
    n = len(w)
    positions = (rng.random() + np.arange(n)) / n
    cum = np.cumsum(w)
    cum[-1] = 1.0
    return np.searchsorted(cum, positions, side="right").astype(np.int64)


def proposal_grid(cfg: GMappingConfig) -> NDArray[np.float64]:
    """Offsets ``(K, 3)`` of the improved proposal's samples around the mode."""

    def axis(rng_: float, step: float) -> NDArray[np.float64]:
        if rng_ <= 0.0:
            return np.zeros(1)
        return np.arange(-rng_, rng_ + 0.5 * step, step)

    xs = axis(cfg.llsamplerange, cfg.llsamplestep)
    ts = axis(cfg.lasamplerange, cfg.lasamplestep)
    g = np.stack(np.meshgrid(xs, xs, ts, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.ascontiguousarray(g)


class GMappingBackend:
    """GMapping as a scanguard `Backend` (see the module docstring).

    Args:
        config: Parameters (ROS names and defaults).
        laser_offset: Pose of the laser in the robot frame.
        initial_pose: Robot pose of the first scan.
        range_max: The sensor's maximum range, used when ``config.maxRange`` is None.
    """

    def __init__(
        self,
        config: GMappingConfig | None = None,
        *,
        laser_offset: ArrayLike = (0.0, 0.0, 0.0),
        initial_pose: ArrayLike = (0.0, 0.0, 0.0),
        range_max: float | None = None,
    ) -> None:
        self.config = cfg = (config or GMappingConfig()).model_copy()
        self.laser_offset = as_pose(laser_offset).reshape(3).copy()
        self.initial_pose = as_pose(initial_pose).reshape(3).copy()
        self._range_max = range_max
        n = cfg.particles
        self._rng = np.random.default_rng(cfg.seed)
        x0, y0 = float(self.initial_pose[0]), float(self.initial_pose[1])
        self.maps = PatchMaps(
            n, cfg.delta, (x0 + cfg.xmin, y0 + cfg.ymin, x0 + cfg.xmax, y0 + cfg.ymax)
        )
        self.poses = np.tile(self.initial_pose, (n, 1))
        self._prev_poses = self.poses.copy()
        self.log_weights = np.zeros(n)
        self.weight_sums = np.zeros(n)
        self._grid = proposal_grid(cfg) if cfg.proposal == "improved" else np.zeros((0, 3))
        # odometry bookkeeping (processScan's m_odoPose, m_lastPartPose, distance counters)
        self._odo: NDArray[np.float64] | None = None
        self._odo_at_update: NDArray[np.float64] | None = None
        self._linear = 0.0
        self._angular = 0.0
        self._last_update_stamp = -math.inf
        # trajectory tree: per processed scan, the particles' poses and, per particle after
        # that update, which of those poses it descends from
        self._node_poses: list[NDArray[np.float64]] = []
        self._node_links: list[NDArray[np.int64]] = []
        self._node_scan: list[int] = []
        # per scan given (compact buffers: these grow with the recording); the scans kept are
        # the processed ones only (the map is rebuilt from them)
        self._scan_update = Rows(np.int64)
        self._scan_odom = Rows(np.float64, (3,))
        self._scans: list[LaserScan] = []
        self._used = Rows(np.bool_)
        self._nonfinite_odometry = 0
        # the fused motion's covariance of the next step, and summed since the last update
        self._next_cov: NDArray[np.float64] | None = None
        self._cov_since_update: NDArray[np.float64] | None = None
        self.last_neff = float(n)
        self._released = False
        self.stats: dict[str, float] = {
            "scans": 0,
            "updates": 0,
            "resamples": 0,
            "rejected": 0,
            "failed_matches": 0,
            "update_seconds": 0.0,
            "peak_pool_mb": 0.0,
        }
        self._update_seconds = Rows(np.float64)

    # --- Backend protocol ----------------------------------------------------------------

    @property
    def name(self) -> str:
        """``gmapping``."""
        return "gmapping"

    def _would_trigger(self, stamp: float, odom: NDArray[np.float64] | None) -> bool:
        cfg = self.config
        if not self._node_scan or odom is None or self._odo is None:
            return True
        move = odom - self._odo
        lin = self._linear + math.hypot(move[0], move[1])
        ang = self._angular + abs(math.atan2(math.sin(move[2]), math.cos(move[2])))
        return bool(
            lin >= cfg.linearUpdate
            or ang >= cfg.angularUpdate
            or (cfg.temporalUpdate >= 0.0 and stamp - self._last_update_stamp > cfg.temporalUpdate)
        )

    def wants_scan(self, stamp: float, odometry: ArrayLike | None) -> bool:
        """Whether `update` would process this scan (the loop judges only those)."""
        return self._would_trigger(stamp, finite_odometry(odometry))

    def update(
        self,
        scan: LaserScan,
        odometry: ArrayLike | None,
        *,
        usable: bool = True,
        match: NDArray[np.float64] | None = None,
    ) -> None:
        """Feed the next scan (``match`` is not used: each particle matches against its map)."""
        if self._released:
            raise ConfigError("GMappingBackend.update after release_particle_maps")
        t0 = time.perf_counter()
        cfg = self.config
        index = len(self._scan_update)
        nonfinite_before = self._nonfinite_odometry
        odom, self._nonfinite_odometry = checked_odometry(
            odometry, self._odo, index, self._nonfinite_odometry
        )
        # no usable odometry with this scan: the motion triggers cannot judge it
        odom_missing = odometry is None or self._nonfinite_odometry > nonfinite_before
        if self._odo is None:
            self._odo = odom.copy()
        else:
            self._move_particles(odom)
            move = odom - self._odo
            self._linear += math.hypot(move[0], move[1])
            self._angular += abs(math.atan2(math.sin(move[2]), math.cos(move[2])))
            self._odo = odom.copy()
        trigger = (
            not self._node_scan
            or odom_missing
            or self._linear >= cfg.linearUpdate
            or self._angular >= cfg.angularUpdate
            or (
                cfg.temporalUpdate >= 0.0
                and scan.stamp - self._last_update_stamp > cfg.temporalUpdate
            )
        )
        used = False
        if trigger and usable:
            used = self._process(scan, odom)
        elif trigger:
            self.stats["rejected"] += 1
        self._scan_update.append(len(self._node_scan) - 1)
        self._scan_odom.append(odom)
        self._used.append(used)
        if used:
            self._scans.append(scan)
        self.stats["scans"] += 1
        dt = time.perf_counter() - t0
        self._update_seconds.append(dt)
        self.stats["update_seconds"] += dt
        logger.debug("scan %d: trigger=%s usable=%s used=%s", index, trigger, usable, used)

    def set_motion_covariance(self, covariance: ArrayLike | None) -> None:
        """The covariance ``(3, 3)`` of the next odometry step (the fused motion model's).

        Used with ``motion_noise: fused`` for the next `update` only; None: GMapping's model.
        """
        self._next_cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)

    def _move_particles(self, odom: NDArray[np.float64]) -> None:
        """Every particle by the odometry step, with the model's or the fused step's noise."""
        cfg, cov, self._next_cov = self.config, self._next_cov, None
        assert self._odo is not None  # set by the first update, before any motion
        if cfg.motion_noise != "fused" or cov is None or not np.all(np.isfinite(cov)):
            self.poses = sample_motion(
                self.poses, self._odo, odom, cfg.srr, cfg.srt, cfg.str, cfg.stt, self._rng
            )
            self._cov_since_update = None
            return
        cov = cov * cfg.fused_noise_scale**2
        step = relative(self._odo, odom).reshape(3)
        # a jitter of 1e-12 (1 micrometre, 1 microradian) keeps a rounded covariance positive
        # definite without changing any sigma that matters
        chol = np.linalg.cholesky(0.5 * (cov + cov.T) + 1e-12 * np.eye(3))
        noisy = step[None, :] + self._rng.standard_normal((len(self.poses), 3)) @ chol.T
        noisy[:, 2] = wrap_angle(noisy[:, 2])
        self.poses = compose(self.poses, noisy)
        # the improved proposal's prior: the steps since the last processed scan, summed
        # (their frames differ by at most angularUpdate, a second-order effect)
        acc = self._cov_since_update
        self._cov_since_update = cov if acc is None else acc + cov

    @property
    def pose(self) -> NDArray[np.float64]:
        """Best particle's current pose."""
        return np.asarray(self.poses[self.best_particle()].copy())

    @property
    def trajectory_pose(self) -> NDArray[np.float64]:
        """The last pose of `trajectory`, without building it.

        The best particle's ancestor at the last processed scan, moved by the odometry since
        (`pose` adds the motion model's sampled noise since then; ``map -> odom`` is this pose
        against the odometry).
        """
        if not self._node_scan or not self._scan_odom:
            return self.pose
        u = len(self._node_scan) - 1
        at = self._node_poses[u][int(self._node_links[u][self.best_particle()])]
        base_odom = self._scan_odom[self._node_scan[u]]
        return np.asarray(compose(at, relative(base_odom, self._scan_odom[-1])))

    def best_particle(self) -> int:
        """Index of the particle with the highest accumulated log-likelihood."""
        return int(np.argmax(self.weight_sums))

    def trajectory(self) -> NDArray[np.float64]:
        """Best particle's pose at every scan given (see the module docstring)."""
        return self._history()()

    def _history(self) -> Callable[[], NDArray[np.float64]]:
        """`trajectory` as a function of the history as it is now (its lists copied: cheap).

        The lists only grow and their items are never changed, so the function may run on
        another thread while the filter goes on.
        """
        # the per-scan buffers (`Rows`) copied as arrays: one memcpy each, not a Python list
        scan_update = self._scan_update.values.tolist()
        scan_odom = self._scan_odom.values.copy()
        node_scan, node_poses = list(self._node_scan), list(self._node_poses)
        node_links, best = list(self._node_links), self.best_particle()
        initial = self.initial_pose.copy()

        def trajectory() -> NDArray[np.float64]:
            n = len(scan_update)
            out = np.empty((n, 3))
            if n == 0:
                return out
            # the poses of the best particle's ancestors at every processed scan
            at_update = np.empty((len(node_scan), 3))
            k = best
            for u in range(len(node_scan) - 1, -1, -1):
                j = int(node_links[u][k])
                at_update[u] = node_poses[u][j]
                k = j
            odom = np.asarray(scan_odom)
            for i in range(n):
                u = scan_update[i]
                if u < 0:
                    base_pose, base_odom = initial, odom[0]
                else:
                    base_pose, base_odom = at_update[u], odom[node_scan[u]]
                out[i] = compose(base_pose, relative(base_odom, odom[i]))
            out[:, 2] = wrap_angle(out[:, 2])
            return out

        return trajectory

    @property
    def update_seconds(self) -> NDArray[np.float64]:
        """Per scan given: seconds of its `update`."""
        return np.asarray(self._update_seconds.values.copy())

    def used(self) -> NDArray[np.bool_]:
        """Per scan given: whether it was processed (matched and registered)."""
        return self._used.values.copy()

    def grid(self) -> Any:
        """The best particle's map, rebuilt from its trajectory and the processed scans."""
        return self.map_builder()()[1]

    def map_builder(self) -> Callable[[], tuple[NDArray[np.float64], Any]]:
        """`trajectory` and `grid` as one function of the state now (copied now: cheap).

        A live node takes the copy between two scans and builds the trajectory and the map
        on another thread while the filter goes on (`scanguard.apps.node`); the results are
        `trajectory`'s and `grid`'s, bit for bit.
        """
        from scanguard.slam.grid import GridConfig, OccupancyGrid, build_map

        cfg = self.config
        gcfg = GridConfig(resolution=cfg.delta, max_range=cfg.maxUrange)
        history, used = self._history(), self.used()
        scans = list(self._scans)  # the processed scans, in order (immutable)
        offset = self.laser_offset.copy()

        def build() -> tuple[NDArray[np.float64], Any]:
            traj = history()
            if not used.any():
                origin = (traj[0, 0] - 10.0, traj[0, 1] - 10.0)
                return traj, OccupancyGrid(gcfg, origin=origin)
            poses = traj[np.flatnonzero(used)[: len(scans)]]
            return traj, build_map(scans, poses, offset, config=gcfg)

        return build

    def release_particle_maps(self) -> None:
        """Free the particles' maps once the recording is over (the pool is most of the memory).

        The trajectory, `grid` (rebuilt from the processed scans) and the stats do not read
        them; an `update` after this raises `ConfigError`.
        """
        self._released = True
        self.maps = PatchMaps(1, self.config.delta, (0.0, 0.0, 0.0, 0.0), capacity=16)

    # --- the filter ----------------------------------------------------------------------

    def _beams(self, scan: LaserScan) -> tuple[NDArray[np.float64], ...]:
        ranges = np.where(scan.valid, scan.ranges.astype(np.float64), np.inf)
        a = scan.angles
        return np.ascontiguousarray(ranges), np.cos(a), np.sin(a)

    def _max_range(self, scan: LaserScan) -> float:
        if self.config.maxRange is not None:
            return float(self.config.maxRange)
        return float(self._range_max if self._range_max is not None else scan.range_max)

    def _ensure_map_covers(self, ranges: NDArray[np.float64], usable: float) -> None:
        r = np.minimum(ranges[np.isfinite(ranges)], usable)
        if not len(r):
            return
        lp = compose(self.poses, self.laser_offset)
        # the scan's reach from every particle, plus the matcher's search margin
        reach = float(r.max()) + 1.0
        lo = lp[:, :2].min(axis=0) - reach
        hi = lp[:, :2].max(axis=0) + reach
        self.maps.ensure_contains(np.array([lo, hi]), margin=0.0)

    def _process(self, scan: LaserScan, odom: NDArray[np.float64]) -> bool:
        cfg = self.config
        max_range = self._max_range(scan)
        ranges, ca, sa = self._beams(scan)
        usable = min(cfg.maxUrange, max_range)
        self._ensure_map_covers(ranges, usable)
        m = self.maps
        n = cfg.particles
        if not self._node_scan:
            # first scan: all particles are identical, so register once and share the map
            m.register(0, self.laser_offset, self.poses[0], ranges, ca, sa, usable,
                       max_range)  # fmt: skip
            m.share_from(0)
            self._record_node(scan, odom, np.arange(n))
            return True
        t_match = time.perf_counter()
        with kern.one_particle_chunks():
            modes, scores, lmode, lgrid = kern.match_particles(
                m.tables, m.flags, m.hits, m.accx, m.accy, m.ox, m.oy, m.delta, self.poses,
                self.laser_offset, ranges, ca, sa, usable, cfg.kernelSize, cfg.lskip,
                cfg.sigma, cfg.lsigma, cfg.lstep, cfg.astep, cfg.iterations, self._grid,
            )  # fmt: skip
        self._add_seconds("match_seconds", t_match)
        ok = scores > cfg.minimumScore
        self.stats["failed_matches"] += int(np.sum(~ok))
        centers = np.where(ok[:, None], modes, self.poses)
        if cfg.proposal == "mode":
            if not ok.all():
                # the likelihood where a failed match left the particle (a one-point grid)
                at_pose = self._grid_loglik(self.poses, _NO_OFFSET, ranges, ca, sa, usable)[:, 0]
                lmode = np.where(ok, lmode, at_pose)
            gain = lmode
            self.poses = centers
        else:
            if not ok.all():
                lgrid = lgrid.copy()
                bad = np.flatnonzero(~ok)
                lgrid[bad] = self._grid_loglik(self.poses[bad], self._grid, ranges, ca, sa, usable)
            gain, self.poses = self._improved_proposal(centers, lgrid, odom)
        self.log_weights += gain
        self.weight_sums += gain
        w = normalized_weights(self.log_weights, cfg.ogain)
        self.last_neff = effective_sample_size(w)
        node_poses = self.poses.copy()
        if self.last_neff < cfg.resampleThreshold * n:
            idx = systematic_resample(w, self._rng)
            self.poses = self.poses[idx]
            self.weight_sums = self.weight_sums[idx]
            self.log_weights = np.zeros(n)
            m.resample(idx)
            self.stats["resamples"] += 1
        else:
            idx = np.arange(n)
        t_reg = time.perf_counter()
        m.register_all(np.arange(n), self.laser_offset, self.poses, ranges, ca, sa, usable,
                       max_range)  # fmt: skip
        self._add_seconds("register_seconds", t_reg)
        self._record_node(scan, odom, idx, node_poses)
        self.stats["peak_pool_mb"] = max(self.stats["peak_pool_mb"], m.nbytes / 1e6)
        return True

    def _add_seconds(self, key: str, since: float) -> None:
        """Add the wall time since ``since`` (`time.perf_counter`) to ``stats[key]``."""
        self.stats[key] = self.stats.get(key, 0.0) + time.perf_counter() - since

    def _grid_loglik(
        self,
        poses: NDArray[np.float64],
        grid: NDArray[np.float64],
        ranges: NDArray[np.float64],
        ca: NDArray[np.float64],
        sa: NDArray[np.float64],
        usable: float,
    ) -> NDArray[np.float64]:
        """Log-likelihoods ``(P, K)`` of the scan at ``poses[i] + grid[k]`` in each own map."""
        cfg, m = self.config, self.maps
        with kern.one_particle_chunks():
            out = kern.grid_particles(
                m.tables, m.flags, m.hits, m.accx, m.accy, m.ox, m.oy, m.delta,
                np.ascontiguousarray(poses), self.laser_offset, ranges, ca, sa, usable,
                cfg.kernelSize, cfg.lskip, cfg.sigma, cfg.lsigma, grid,
            )  # fmt: skip
        return np.asarray(out)

    def _improved_proposal(
        self, centers: NDArray[np.float64], lgrid: NDArray[np.float64], odom: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Draw each particle from likelihood x motion prior on the grid around its centre.

        Returns:
            ``(log weight gains (P,), new poses (P, 3))``.
        """
        cfg = self.config
        assert self._odo_at_update is not None
        step = relative(self._odo_at_update, odom).reshape(3)
        if self._cov_since_update is not None:
            sig = np.maximum(np.sqrt(np.abs(np.diag(self._cov_since_update))), _PRIOR_FLOOR)
        else:
            sig = np.maximum(motion_sigma(step, cfg.srr, cfg.srt, cfg.str, cfg.stt), _PRIOR_FLOOR)
        samples = centers[:, None, :] + self._grid[None, :, :]  # (P, K, 3)
        n, k = samples.shape[:2]
        local = relative(np.repeat(self._prev_poses, k, axis=0), samples.reshape(-1, 3)).reshape(
            n, k, 3
        )
        res = local - step
        res[..., 2] = wrap_angle(res[..., 2])
        lprior = -0.5 * np.sum((res / sig) ** 2, axis=-1)
        lw = lgrid + lprior
        top = lw.max(axis=1, keepdims=True)
        e = np.exp(lw - top)
        tot = e.sum(axis=1, keepdims=True)
        gain = (top + np.log(tot)).reshape(n)
        wts = e / tot
        mean_off = np.einsum("pk,kd->pd", wts, self._grid)
        dev = self._grid[None, :, :] - mean_off[:, None, :]
        cov = np.einsum("pk,pkd,pke->pde", wts, dev, dev) + np.diag(_PROPOSAL_JITTER)[None]
        chol = np.linalg.cholesky(cov)
        z = self._rng.standard_normal((n, 3))
        poses = centers + mean_off + np.einsum("pde,pe->pd", chol, z)
        poses[:, 2] = wrap_angle(poses[:, 2])
        return gain, poses

    def _record_node(
        self,
        scan: LaserScan,
        odom: NDArray[np.float64],
        links: NDArray[np.int64],
        node_poses: NDArray[np.float64] | None = None,
    ) -> None:
        self._node_poses.append(self.poses.copy() if node_poses is None else node_poses)
        self._node_links.append(np.asarray(links, dtype=np.int64))
        self._node_scan.append(len(self._scan_update))
        self._prev_poses = self.poses.copy()
        self._odo_at_update = odom.copy()
        self._linear = 0.0
        self._angular = 0.0
        self._last_update_stamp = scan.stamp
        self._cov_since_update = None
        self.stats["updates"] += 1
