"""GMapping's parameters, with the names and defaults of ROS ``slam_gmapping``.

The names are those a ROS user sets in a launch file; the defaults are the ROS node's (not
OpenSLAM's bare library defaults), because that is the GMapping people compare against. Units:
metres, radians, seconds.

Motion-model naming follows the code as ROS runs it (OpenSLAM ``motionmodel.cpp``): per odometry
step ``(dx, dy, dtheta)``, the sampled noise has standard deviations

* ``x``: ``srr*|dx| + str*|dtheta| + 0.3*srr*|dy|``
* ``y``: ``srr*|dy| + str*|dtheta| + 0.3*srr*|dx|``
* ``theta``: ``stt*|dtheta| + srt*sqrt(dx^2 + dy^2)``

(the ROS wiki's one-line descriptions of ``srt`` and ``str`` are swapped with respect to the
code; the code is what a ROS user's parameters actually do).
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from scanguard.config import YamlModel

MAX_EXTENT = 1e5
"""Largest ``|xmin|``, ``|xmax|``, ``|ymin|``, ``|ymax|`` (m) of the initial map."""

MAX_INITIAL_CELLS = 1e8
"""Most cells of the initial map (it grows later as the robot moves)."""

MEMORY_LIMIT_BYTES = 4 * 2**30
"""Most memory the particle filter's maps may be estimated to need (`estimated_map_bytes`)."""

#: Cells per side of a map patch (`scanguard.slam.gmapping._kernels.PATCH`).
PATCH_SIDE = 16
#: Patches one particle writes for itself per update (a lower bound: a scan's beams cross
#: many more); shared patches are copied on a particle's first write.
PATCHES_PER_PARTICLE = 64
#: Bytes per patch cell (hits, visits: int32; x and y sums: float32).
PATCH_CELL_BYTES = 16

MAX_MOTION_NOISE = 10.0
"""Largest odometry noise coefficient (``srr``, ``srt``, ``str``, ``stt``): the defaults are
0.1-0.2; beyond 10 the particles scatter over kilometres per metre driven and the map grows
without bound (a huge value ended in numpy's pad_width TypeError)."""


class GMappingConfig(YamlModel):
    """Parameters of the `gmapping` back end (ROS ``slam_gmapping`` names and defaults).

    Attributes:
        particles: Number of particles.
        delta: Map resolution (m per cell).
        maxUrange: Usable range of the laser (m): longer beams are cut to it, their ends are
            not hits, and the matcher ignores them.
        maxRange: Beams at or beyond this are ignored entirely (None = the sensor's maximum).
        sigma: Standard deviation used by the matcher's score (``exp(-d^2 / sigma)``).
        kernelSize: Search window (cells each way) for the nearest hit of a beam end.
        lstep: Initial linear step of the hill-climbing matcher (m).
        astep: Initial angular step of the hill-climbing matcher (rad).
        iterations: Step refinements of the hill climber.
        lsigma: Standard deviation of the per-beam likelihood (weights).
        ogain: Gain that smooths the likelihood when normalising weights.
        lskip: Use one beam in ``lskip + 1`` for matching.
        minimumScore: A match scoring at or below this is ignored (odometry pose kept).
        srr: Odometry noise, translation from translation.
        srt: Odometry noise, rotation from translation (see module docstring).
        str: Odometry noise, translation from rotation (see module docstring).
        stt: Odometry noise, rotation from rotation.
        linearUpdate: Process a scan after this much travel (m).
        angularUpdate: Process a scan after this much rotation (rad).
        temporalUpdate: Also process a scan after this long (s); negative = never.
        resampleThreshold: Resample when Neff < resampleThreshold * particles.
        xmin: Initial map extent (m); the map grows as needed.
        ymin: Initial map extent (m).
        xmax: Initial map extent (m).
        ymax: Initial map extent (m).
        llsamplerange: Half-width of the improved proposal's translational sample grid (m).
        llsamplestep: Step of that grid (m).
        lasamplerange: Half-width of the angular sample grid (rad).
        lasamplestep: Step of the angular grid (rad).
        occ_thresh: Hit ratio above which a cell of the exported map is occupied.
        proposal: ``improved``: sample each particle around the mode its scan match found, from
            the Gaussian fitted to likelihood x motion model on the sample grid, and weight it
            by the grid's total (Grisetti et al. 2007); ``mode`` (default since session 12):
            move the particle to the mode and weight it by the likelihood there (OpenSLAM's
            shortcut, what slam_gmapping runs). Chosen leave one log out, every fold (mean over
            filter seeds 0-2, the guarded default: Intel 0.0386 -> 0.0361, FR079 0.0603 ->
            0.0591, ACES 0.0551 -> 0.0455 m) and 14-18 % faster per update (README).
        seed: Seed of the particle filter's random numbers (same seed, same run).
        motion_noise: ``model``: each particle's motion noise comes from ``srr``, ``srt``,
            ``str``, ``stt`` on the odometry step (GMapping's model); ``fused``: from the
            covariance the fused motion model hands over with each step
            (`GMappingBackend.set_motion_covariance`), times ``fused_noise_scale``, with the
            model where none is given. Measured, not the default: with the fused default's
            confident matches the particles barely spread, and one filter seed in three lost
            ACES (0.43 m) and Intel (0.094 m) where GMapping's model held (README).
        fused_noise_scale: Scale of the fused covariance's sigmas (``motion_noise: fused``).
    """

    particles: int = Field(default=30, ge=1, le=10000)
    delta: float = Field(default=0.05, gt=0.0, le=1.0)
    maxUrange: float = Field(default=80.0, gt=0.0, le=1000.0)
    maxRange: float | None = Field(default=None, gt=0.0, le=1000.0)
    sigma: float = Field(default=0.05, gt=0.0)
    kernelSize: int = Field(default=1, ge=0, le=10)
    lstep: float = Field(default=0.05, gt=0.0)
    astep: float = Field(default=0.05, gt=0.0)
    iterations: int = Field(default=5, ge=0, le=50)
    lsigma: float = Field(default=0.075, gt=0.0)
    ogain: float = Field(default=3.0, gt=0.0)
    lskip: int = Field(default=0, ge=0)
    minimumScore: float = Field(default=0.0, ge=0.0)
    srr: float = Field(default=0.1, ge=0.0, le=MAX_MOTION_NOISE)
    srt: float = Field(default=0.2, ge=0.0, le=MAX_MOTION_NOISE)
    str: float = Field(default=0.1, ge=0.0, le=MAX_MOTION_NOISE)
    stt: float = Field(default=0.2, ge=0.0, le=MAX_MOTION_NOISE)
    linearUpdate: float = Field(default=1.0, ge=0.0)
    angularUpdate: float = Field(default=0.5, ge=0.0)
    temporalUpdate: float = -1.0
    resampleThreshold: float = Field(default=0.5, ge=0.0, le=1.0)
    xmin: float = -100.0
    ymin: float = -100.0
    xmax: float = 100.0
    ymax: float = 100.0
    llsamplerange: float = Field(default=0.01, ge=0.0)
    llsamplestep: float = Field(default=0.01, gt=0.0)
    lasamplerange: float = Field(default=0.005, ge=0.0)
    lasamplestep: float = Field(default=0.005, gt=0.0)
    occ_thresh: float = Field(default=0.25, gt=0.0, lt=1.0)
    proposal: Literal["improved", "mode"] = "mode"
    seed: int = Field(default=0, ge=0, le=2**63 - 1)
    motion_noise: Literal["model", "fused"] = "model"
    fused_noise_scale: float = Field(default=1.0, gt=0.0, le=100.0)

    @model_validator(mode="after")
    def _check(self) -> GMappingConfig:
        if not (self.xmin < self.xmax and self.ymin < self.ymax):
            raise ValueError("xmin < xmax and ymin < ymax are required")
        for name in ("xmin", "ymin", "xmax", "ymax", "temporalUpdate"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        for name in ("xmin", "ymin", "xmax", "ymax"):
            if abs(getattr(self, name)) > MAX_EXTENT:
                raise ValueError(f"{name} must lie within +-{MAX_EXTENT:.0e} m")
        cells = (self.xmax - self.xmin) * (self.ymax - self.ymin) / self.delta**2
        if cells > MAX_INITIAL_CELLS:
            # the initial map is allocated at once, per particle: refuse before gigabytes
            raise ValueError(
                f"initial map of {cells:.3g} cells (xmin..xmax x ymin..ymax at delta "
                f"{self.delta} m) exceeds {MAX_INITIAL_CELLS:.0e}; the map grows as needed"
            )
        need = estimated_map_bytes(self)
        if need > MEMORY_LIMIT_BYTES:
            # --particles 10000 reached 3 GB in 10 s: refuse before allocating, say what to lower
            raise ValueError(
                f"{self.particles} particles need about {need / 2**30:.1f} GiB for their maps "
                f"(the patch table of a {self.xmax - self.xmin:g} x {self.ymax - self.ymin:g} m "
                f"initial map and their own patches each), more than the "
                f"{MEMORY_LIMIT_BYTES / 2**30:g} GiB limit: lower particles (--particles) or the "
                "initial map (xmin..xmax, ymin..ymax)"
            )
        return self


def estimated_map_bytes(cfg: GMappingConfig) -> float:
    """A lower bound of the memory the particles' maps take once the filter runs.

    Every particle has a patch table over the initial map (int32 per patch) and, after each
    update, patches of its own (`PATCHES_PER_PARTICLE`); see
    `scanguard.slam.gmapping.maps.PatchMaps`.
    """
    patch_m = cfg.delta * PATCH_SIDE
    tiles = (math.ceil((cfg.xmax - cfg.xmin) / patch_m) + 1) * (
        math.ceil((cfg.ymax - cfg.ymin) / patch_m) + 1
    )
    own = PATCHES_PER_PARTICLE * PATCH_SIDE**2 * PATCH_CELL_BYTES
    return float(cfg.particles) * (4.0 * tiles + own)
