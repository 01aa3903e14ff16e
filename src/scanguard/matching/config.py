"""Matcher settings: `ICPConfig` and `CorrelativeConfig`.

The ICP's has the paper's stop rule as a preset and a proper convergence test by default.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import ConfigDict, Field, model_validator

from scanguard.config import YamlModel
from scanguard.errors import ConfigError


class ICPConfig(YamlModel):
    """Settings shared by the point-to-point and point-to-line ICPs.

    Attributes:
        max_iterations: Hard cap on iterations (the paper: 20).
        stop_rule: ``"paper"`` stops when the translation of the last update
            ``||mu_Q - R mu_P||`` is below ``translation_tol`` (rotation is ignored, as in the
            paper); ``"both"`` needs the translation *and* the rotation of the last update below
            their tolerances.
        translation_tol: Translation tolerance of the stop rule (m).
        rotation_tol_deg: Rotation tolerance of the ``"both"`` rule (degrees).
        max_correspondence_distance: Pairs farther apart are not used (m); None = no limit
            (the paper: every source point is paired with its true nearest neighbour).
        inlier_threshold: Distance (m) under which a final pair counts as an inlier (overlap).
        min_points: Fewer valid points than this in either scan: no match, flagged.
        cell_size: Edge of the nearest-neighbour grid cells (m); speed only, never the answer.
        normal_radius: Size (m) of the neighbourhoods that give target normals (used by the
            point-to-line ICP and by the Hessian of every result): the 2x2 block of grid cells
            around the point when ``cell_size <= normal_radius``, else (and for sparse points)
            the disc of this radius, grown until it holds 3 points.
        trim_fraction: Point-to-line only: fraction of pairs kept, the closest ones (1 = all).
        huber_delta: Point-to-line only: Huber kernel width (m) on point-to-line residuals;
            0 disables the kernel.
        threads: Parallel chunks for the nearest-neighbour search of each iteration (numba
            ``prange``; opt-in). 1 = the serial loop. With more, the sums are still reduced
            serially in source order, so estimates equal the single-thread ones (tested to
            1e-9) and do not vary from run to run. Worker threads come from numba's pool
            (``numba.get_num_threads()``); the final statistics stay serial.
    """

    max_iterations: int = Field(default=20, ge=1, le=1000)
    stop_rule: Literal["paper", "both"] = "both"
    translation_tol: float = Field(default=1e-3, gt=0)
    rotation_tol_deg: float = Field(default=0.01, gt=0)
    max_correspondence_distance: float | None = Field(default=None, gt=0)
    inlier_threshold: float = Field(default=0.05, gt=0)
    min_points: int = Field(default=5, ge=3)
    cell_size: float = Field(default=0.15, gt=0)
    normal_radius: float = Field(default=0.15, gt=0)
    trim_fraction: float = Field(default=0.9, gt=0, le=1)
    huber_delta: float = Field(default=0.05, ge=0)
    threads: int = Field(default=1, ge=1, le=64)

    @classmethod
    def paper(cls) -> ICPConfig:
        """Jeong & Lee (2023) Sec. 2.2: at most 20 iterations, stop when ``err < 0.01 m``.

        ``err = ||mu_Q - R mu_P||`` is the translation of the last update; rotation is not
        tested, so a match can stop with part of its rotation uncorrected (by design: the
        detector must be able to judge exactly the paper's matcher).
        """
        return cls(max_iterations=20, stop_rule="paper", translation_tol=0.01)


class CorrelativeConfig(YamlModel):
    """Settings of the correlative matcher.

    Attributes:
        resolution: Finest grid cell (m); also the translation step of the search.
        levels: Branch-and-bound pyramid depth: the coarsest level's cell is
            ``resolution * 2**(levels - 1)``. 1 = exhaustive search at the finest level.
            Large windows want more levels (e.g. 6-7 for a +-4 m loop search).
        window_xy: Search ``+-`` this (m) in x and in y around the initial pose.
        window_theta: Search ``+-`` this (rad) around the initial heading (``>= pi``: the
            whole circle, without duplicated angles).
        theta_step: Angular step (rad); None = Cartographer's rule
            ``acos(1 - r^2 / (2 d_max^2))`` with ``d_max`` the farthest source point, so the
            farthest point moves by at most one cell per step.
        sigma: Smearing of map points in the likelihood table (m).
        min_score: A best pose whose mean response is below this is not reported as found
            (the search also prunes with it, so a high value makes failing searches fast).
        refine: `match_to_map` refines the correlative pose with point-to-line ICP against the
            grid's map points.
        max_range: Source points farther than this from the sensor are dropped (m); None =
            keep all.
    """

    # non-finite values are refused by `_check` as a ConfigError (which direct constructors,
    # e.g. a matcher's options, catch as one ScanGuardError), not by the base's field check
    model_config = ConfigDict(allow_inf_nan=True)

    resolution: float = 0.02
    levels: int = 4
    window_xy: float = 0.3
    window_theta: float = 0.35
    theta_step: float | None = None
    sigma: float = 0.05
    min_score: float = 0.0
    refine: bool = True
    max_range: float | None = None

    @model_validator(mode="after")
    def _check(self) -> CorrelativeConfig:
        # ConfigError (not a pydantic ValueError) so that callers catch one ScanGuardError
        checks = [
            ("resolution", self.resolution, self.resolution > 0, "must be > 0"),
            ("levels", self.levels, 1 <= self.levels <= 16, "must be in 1..16"),
            ("window_xy", self.window_xy, self.window_xy >= 0, "must be >= 0"),
            ("window_theta", self.window_theta, self.window_theta >= 0, "must be >= 0"),
            ("sigma", self.sigma, self.sigma > 0, "must be > 0"),
            ("min_score", self.min_score, True, ""),
        ]
        if self.theta_step is not None:
            checks.append(("theta_step", self.theta_step, self.theta_step > 0, "must be > 0"))
        if self.max_range is not None:
            checks.append(("max_range", self.max_range, self.max_range > 0, "must be > 0"))
        for name, value, ok, rule in checks:
            if not math.isfinite(value):
                raise ConfigError(f"CorrelativeConfig.{name}: must be finite, got {value}")
            if not ok:
                raise ConfigError(f"CorrelativeConfig.{name}: {rule}, got {value}")
        return self
