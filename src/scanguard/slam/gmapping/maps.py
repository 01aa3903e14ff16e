"""Per-particle occupancy maps that share memory: a pool of copy-on-write patches.

`PatchMaps` owns the pool and one patch table per particle (see `_kernels` for the layout).
Resampling copies only the tables and bumps reference counts; a particle's first write into
a shared patch copies that patch. Live memory is therefore the union of the distinct patches
the surviving particles still reference, not ``particles x map``.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

import scanguard.slam.gmapping._kernels as kern
import scanguard.slam.gmapping._register as reg

logger = logging.getLogger(__name__)


class PatchMaps:
    """The maps of all particles of one filter.

    Args:
        n_particles: Number of particles (tables).
        delta: Cell size (m).
        bounds: Initial extent ``(xmin, ymin, xmax, ymax)`` (m); grows on demand.
        capacity: Initial number of patches in the pool (grows by doubling).
    """

    #: Free ids a particle's block holds beyond the mean a particle took in the last
    #: comparable registration (see `register_all`).
    block_extra = 16

    def __init__(
        self,
        n_particles: int,
        delta: float,
        bounds: tuple[float, float, float, float],
        capacity: int = 1024,
    ) -> None:
        self.delta = float(delta)
        self.patch_m = self.delta * kern.PATCH
        xmin, ymin, xmax, ymax = bounds
        self.ox = math.floor(xmin / self.patch_m) * self.patch_m
        self.oy = math.floor(ymin / self.patch_m) * self.patch_m
        tx = max(1, math.ceil((xmax - self.ox) / self.patch_m))
        ty = max(1, math.ceil((ymax - self.oy) / self.patch_m))
        self.tables = np.full((n_particles, ty, tx), -1, dtype=np.int32)
        cap = max(16, int(capacity))
        # `kern.cell_flags` of every cell, kept by the registration: the matcher reads one byte
        # per cell instead of comparing hits against visits
        self.flags = np.zeros((cap, kern.PATCH_CELLS), dtype=np.uint8)
        self.hits = np.zeros((cap, kern.PATCH_CELLS), dtype=np.int32)
        self.visits = np.zeros((cap, kern.PATCH_CELLS), dtype=np.int32)
        self.accx = np.zeros((cap, kern.PATCH_CELLS), dtype=np.float32)
        self.accy = np.zeros((cap, kern.PATCH_CELLS), dtype=np.float32)
        self.refs = np.zeros(cap, dtype=np.int32)
        self.free = np.arange(cap - 1, -1, -1, dtype=np.int32)
        self.nfree = np.array([cap], dtype=np.int64)
        # new patches a particle took on average in the last registration right after a
        # resampling (which shares every patch, so the next scan copies many) and in the last
        # one otherwise: they size the next blocks (the mean, not the most, so that 30
        # particles do not each reserve the worst case)
        self._last_new = {True: 0, False: 0}
        self._resampled = False

    @property
    def capacity(self) -> int:
        """Patches in the pool (live and free)."""
        return int(self.refs.shape[0])

    @property
    def live_patches(self) -> int:
        """Patches referenced by at least one particle."""
        return self.capacity - int(self.nfree[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the pool and the tables."""
        arrays = (
            self.flags,
            self.hits,
            self.visits,
            self.accx,
            self.accy,
            self.refs,
            self.free,
            self.tables,
        )
        return int(sum(a.nbytes for a in arrays))

    def _grow_pool(self, need: int) -> None:
        old = self.capacity
        new = old
        # by an eighth rather than doubling: the blocks of `register_all` ask for a lot at once
        # and give most of it back, so a doubled pool would mostly stay free
        while new - old + int(self.nfree[0]) < need:
            new += max(16, new // 8)
        extra = new - old

        def grow(a: NDArray[np.generic]) -> NDArray[np.generic]:
            return np.concatenate([a, np.zeros((extra, *a.shape[1:]), dtype=a.dtype)])

        self.flags = grow(self.flags)  # type: ignore[assignment]
        self.hits = grow(self.hits)  # type: ignore[assignment]
        self.visits = grow(self.visits)  # type: ignore[assignment]
        self.accx = grow(self.accx)  # type: ignore[assignment]
        self.accy = grow(self.accy)  # type: ignore[assignment]
        self.refs = grow(self.refs)  # type: ignore[assignment]
        nf = int(self.nfree[0])
        free = np.empty(new, dtype=np.int32)
        free[:nf] = self.free[:nf]
        free[nf : nf + extra] = np.arange(new - 1, old - 1, -1, dtype=np.int32)
        self.free = free
        self.nfree[0] = nf + extra
        logger.debug("patch pool grown to %d patches (%.1f MB)", new, self.nbytes / 1e6)

    def ensure_contains(self, points: ArrayLike, margin: float = 2.0) -> None:
        """Grow every table (by whole patches) so that ``points`` (m, ``(M, 2)``) are inside."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        if not len(p):
            return
        lo = p.min(axis=0) - margin
        hi = p.max(axis=0) + margin
        _, ty, tx = self.tables.shape
        add_x0 = max(0, math.ceil((self.ox - lo[0]) / self.patch_m))
        add_y0 = max(0, math.ceil((self.oy - lo[1]) / self.patch_m))
        add_x1 = max(0, math.ceil((hi[0] - (self.ox + tx * self.patch_m)) / self.patch_m))
        add_y1 = max(0, math.ceil((hi[1] - (self.oy + ty * self.patch_m)) / self.patch_m))
        if add_x0 or add_y0 or add_x1 or add_y1:
            # grow by at least a quarter of the current size, so a robot that keeps exploring
            # does not pay for one re-allocation per update
            if add_x0 or add_x1:
                q = max(1, tx // 4)
                add_x0, add_x1 = (
                    (max(add_x0, q) if add_x0 else 0),
                    (max(add_x1, q) if add_x1 else 0),
                )
            if add_y0 or add_y1:
                q = max(1, ty // 4)
                add_y0, add_y1 = (
                    (max(add_y0, q) if add_y0 else 0),
                    (max(add_y1, q) if add_y1 else 0),
                )
            self.tables = np.pad(
                self.tables, ((0, 0), (add_y0, add_y1), (add_x0, add_x1)), constant_values=-1
            )
            self.ox -= add_x0 * self.patch_m
            self.oy -= add_y0 * self.patch_m

    def register(
        self,
        particle: int,
        laser_pose_robot: NDArray[np.float64],
        pose: NDArray[np.float64],
        ranges: NDArray[np.float64],
        ca: NDArray[np.float64],
        sa: NDArray[np.float64],
        usable: float,
        max_range: float,
    ) -> None:
        """Integrate one scan into one particle's map (see `register_all`)."""
        self.register_all(
            [particle], laser_pose_robot, np.asarray(pose)[None], ranges, ca, sa, usable,
            max_range,
        )  # fmt: skip

    def register_all(
        self,
        particles: ArrayLike,
        laser_pose_robot: NDArray[np.float64],
        poses: NDArray[np.float64],
        ranges: NDArray[np.float64],
        ca: NDArray[np.float64],
        sa: NDArray[np.float64],
        usable: float,
        max_range: float,
    ) -> None:
        """Integrate one scan into the maps of ``particles`` at ``poses`` (``(M, 3)``).

        One parallel kernel call (`_register.register_particles`) per round: each particle
        gets a block of free patch ids; one that runs short stops before a beam and the
        unfinished ones go on in another round with blocks twice as large.
        """
        which = np.asarray(particles, dtype=np.int64).reshape(-1)
        poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 3)
        finite = ranges[(ranges <= max_range) & (ranges > 0.0)]
        if not len(finite):
            return
        longest = min(float(finite.max()), usable) / self.delta + 2.0
        # a block must hold at least the patches of the longest beam, or no beam could start;
        # beyond that, what a particle took last time: the unused rest is pool overhead
        expect = self._last_new[self._resampled] + self.block_extra
        quota = max(int(reg.beam_patches(int(longest) + 1)), expect)
        starts = np.zeros(len(which), dtype=np.int64)
        taken = 0
        n = len(which)
        while len(which):
            taken += self._register_round(
                which, starts, quota, laser_pose_robot, poses, ranges, ca, sa, usable, max_range
            )
            todo = starts >= 0
            which, starts, poses = which[todo], starts[todo], poses[todo]
            quota *= 2
        self._last_new[self._resampled] = -(-taken // n)
        self._resampled = False

    def _register_round(
        self,
        which: NDArray[np.int64],
        starts: NDArray[np.int64],
        quota: int,
        laser_pose_robot: NDArray[np.float64],
        poses: NDArray[np.float64],
        ranges: NDArray[np.float64],
        ca: NDArray[np.float64],
        sa: NDArray[np.float64],
        usable: float,
        max_range: float,
    ) -> int:
        """One `register_all` round; returns the new patches the particles took in all."""
        m = len(which)
        if self.nfree[0] < m * quota:
            self._grow_pool(m * quota)
        nf = int(self.nfree[0])
        # the top of the free stack, one row per particle, in particle order
        blocks = np.ascontiguousarray(self.free[nf - m * quota : nf].reshape(m, quota))
        self.nfree[0] = nf - m * quota
        left = np.full(m, quota, dtype=np.int64)
        copied = np.zeros((m, quota + 1), dtype=np.int32)
        with kern.one_particle_chunks():
            reg.register_particles(
                which, self.tables, self.flags, self.hits, self.visits, self.accx, self.accy,
                self.refs, blocks, left, copied, starts, self.ox, self.oy, self.delta, poses,
                laser_pose_robot, ranges, ca, sa, usable, max_range,
            )  # fmt: skip
        # unused ids back onto the free stack (row-major: the same order every run)
        unused = blocks[np.arange(quota)[None, :] < left[:, None]]
        nf = int(self.nfree[0])
        self.free[nf : nf + len(unused)] = unused
        self.nfree[0] = nf + len(unused)
        reg.release_copied(copied, self.refs, self.free, self.nfree)
        return int(m * quota - left.sum())

    def share_from(self, source: int) -> None:
        """Make every particle's map the one of ``source`` (shared, no copy)."""
        self.resample(np.full(self.tables.shape[0], source, dtype=np.int64))

    def resample(self, indices: ArrayLike) -> None:
        """New particle ``k`` takes the map of old particle ``indices[k]`` (shared patches)."""
        idx = np.asarray(indices, dtype=np.int64)
        new = np.ascontiguousarray(self.tables[idx])
        reg.retain_tables(new, self.refs)
        reg.release_tables(self.tables, self.refs, self.free, self.nfree)
        self.tables = new
        self._resampled = True

    def cell_arrays(self, particle: int) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
        """Dense ``(hits, visits)`` of one particle's map, rows = y (origin ``ox, oy``)."""
        table = self.tables[particle]
        ty, tx = table.shape
        hits = np.zeros((ty * kern.PATCH, tx * kern.PATCH), dtype=np.int32)
        visits = np.zeros_like(hits)
        for py, px in zip(*np.nonzero(table >= 0), strict=True):
            pid = table[py, px]
            n = kern.PATCH
            sl = (slice(py * n, (py + 1) * n), slice(px * n, (px + 1) * n))
            hits[sl] = self.hits[pid].reshape(kern.PATCH, kern.PATCH)
            visits[sl] = self.visits[pid].reshape(kern.PATCH, kern.PATCH)
        return hits, visits
