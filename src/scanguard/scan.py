"""Core data types: one `LaserScan`, and a time-aligned `ScanSequence` of them."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanguard.errors import ScanError

# beam angles per (angle_min, angle_increment, n_beams): one array per sensor layout
_ANGLES: dict[tuple[float, float, int], NDArray[np.float64]] = {}

MAX_FOV_DEG = 360.0
"""Largest field of view (first to last beam) a scan may cover, in degrees."""
_FOV_TOLERANCE_DEG = 1e-3  # float32 increments of a full turn round a hair above 360


@dataclass(frozen=True)
class SensorInfo:
    """Static description of a 2D laser scanner.

    Attributes:
        name: Free-form model name (e.g. ``"RPLidar A3"``).
        n_beams: Beams per scan.
        angle_min: Angle of the first beam (rad, sensor frame, counter-clockwise).
        angle_increment: Angle between beams (rad, > 0).
        range_min: Smallest valid range (m).
        range_max: Largest valid range (m).
        rate_hz: Nominal scan rate, if known.
    """

    name: str
    n_beams: int
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    rate_hz: float | None = None

    @property
    def angle_max(self) -> float:
        """Angle of the last beam (rad)."""
        return self.angle_min + (self.n_beams - 1) * self.angle_increment

    @property
    def fov_deg(self) -> float:
        """Field of view in degrees, first to last beam (never negative)."""
        return float(abs(np.degrees(self.angle_max - self.angle_min)))


@dataclass(frozen=True, eq=False)
class LaserScan:
    """One 2D laser scan, like ``sensor_msgs/LaserScan``.

    Ranges are kept exactly as measured. A beam is *valid* only if it is finite and within
    ``[range_min, range_max]``; NaN, inf and out-of-limit beams never become points, nor
    does a range of 0 or less. A negative ``range_min`` is read as 0; limits that leave no
    valid range (``range_max <= 0`` or ``range_min > range_max``) are a `ScanError`.

    Construction refuses (`ScanError`) zero beams, a non-finite stamp, a zero or non-finite
    ``angle_increment``, non-finite range limits, and a field of view (first to last beam)
    outside ``(0, 360]`` degrees (a one-beam scan has none and is accepted).

    Attributes:
        stamp: Acquisition time (s).
        ranges: Ranges (m), shape ``(n_beams,)``, float32.
        angle_min: Angle of the first beam (rad).
        angle_increment: Angle between consecutive beams (rad, non-zero).
        range_min: Smallest valid range (m).
        range_max: Largest valid range (m).
        intensities: Optional intensities, same length as ``ranges``.
    """

    stamp: float
    ranges: NDArray[np.float32]
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    intensities: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        # An own, read-only copy: the derived arrays below are computed once and cached, so
        # the ranges must never change under them.
        try:
            with np.errstate(over="ignore"):  # float64 beyond float32 becomes inf: invalid
                r = np.array(self.ranges, dtype=np.float32).reshape(-1)
        except (TypeError, ValueError):
            raise ScanError(
                f"scan ranges must be numbers, got {type(self.ranges).__name__}"
            ) from None
        r.flags.writeable = False
        object.__setattr__(self, "ranges", r)
        object.__setattr__(self, "_cache", {})
        if not np.isfinite(self.stamp):
            raise ScanError(f"scan has a non-finite stamp ({self.stamp})")
        if r.size == 0:
            raise ScanError(f"scan at stamp {self.stamp:.6f} has zero beams")
        if not np.isfinite(self.angle_increment) or self.angle_increment == 0.0:
            raise ScanError(
                f"scan at stamp {self.stamp:.6f} has invalid angle_increment {self.angle_increment}"
            )
        if not (np.isfinite(self.range_min) and np.isfinite(self.range_max)):
            raise ScanError(f"scan at stamp {self.stamp:.6f} has non-finite range limits")
        if self.range_max <= 0 or self.range_min > self.range_max:
            # no beam could ever be valid: name the cause instead of an empty scan
            raise ScanError(
                f"scan at stamp {self.stamp:.6f} has range limits {self.range_min:.6g} .. "
                f"{self.range_max:.6g} m: no beam can be valid (range_max must be > 0 and "
                ">= range_min)"
            )
        if self.range_min < 0:
            # a negative minimum would make ranges of 0 and below points; readers warn
            object.__setattr__(self, "range_min", 0.0)
        if not np.isfinite(self.angle_min):
            raise ScanError(f"scan at stamp {self.stamp:.6f} has a non-finite angle_min")
        fov = abs(float(np.degrees((r.size - 1) * self.angle_increment)))
        if fov > MAX_FOV_DEG + _FOV_TOLERANCE_DEG:
            raise ScanError(
                f"scan at stamp {self.stamp:.6f} has a field of view of {fov:.6g} deg "
                f"({r.size} beams, increment {np.degrees(self.angle_increment):.6g} deg); "
                "it must lie in (0, 360] deg"
            )
        if self.intensities is not None:
            inten = np.ascontiguousarray(self.intensities, dtype=np.float32).reshape(-1)
            # drivers often publish empty intensities; keep none rather than invent values
            object.__setattr__(self, "intensities", inten if inten.size == r.size else None)

    def __reduce__(self) -> tuple[Any, ...]:
        # another process (a back end in a worker) gets the measurement, not this process's
        # cached arrays: they are recomputed there, identically and read-only
        return (
            type(self),
            (
                self.stamp,
                self.ranges,
                self.angle_min,
                self.angle_increment,
                self.range_min,
                self.range_max,
                self.intensities,
            ),
        )

    @property
    def n_beams(self) -> int:
        """Number of beams."""
        return int(self.ranges.size)

    @property
    def angle_max(self) -> float:
        """Angle of the last beam (rad)."""
        return self.angle_min + (self.n_beams - 1) * self.angle_increment

    def _cached(self, key: str, make: Callable[[], NDArray[Any]]) -> NDArray[Any]:
        # Derived arrays are computed once per scan (the online loop asks for the points of
        # each scan up to eight times: ICP, three image scales, GMapping feature) and handed
        # out read-only, so that no caller can corrupt them for the others.
        cache: dict[str, NDArray[Any]] = self._cache  # type: ignore[attr-defined]
        out = cache.get(key)
        if out is None:
            out = make()
            out.flags.writeable = False
            cache[key] = out
        return out

    def release(self) -> None:
        """Drop the cached derived arrays (points, validity mask) to free their memory.

        They are computed again, identically, when asked for. The run loop releases each scan
        once it is done with it, so a long recording keeps only its ranges in memory.
        """
        self._cache.clear()  # type: ignore[attr-defined]

    @property
    def angles(self) -> NDArray[np.float64]:
        """Beam angles (rad), shape ``(n_beams,)`` (read-only, shared by same-layout scans)."""
        key = (self.angle_min, self.angle_increment, self.n_beams)
        out = _ANGLES.get(key)
        if out is None:
            out = self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)
            out.flags.writeable = False
            if len(_ANGLES) >= 64:  # a handful of sensor layouts per process, in practice
                _ANGLES.clear()
            _ANGLES[key] = out
        return out

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Validity mask: finite, > 0 and within ``[range_min, range_max]`` (read-only)."""

        def make() -> NDArray[np.bool_]:
            r = self.ranges
            with np.errstate(invalid="ignore"):
                within = (r >= self.range_min) & (r <= self.range_max)
                return np.isfinite(r) & (r > 0) & within

        return self._cached("valid", make)

    @property
    def invalid_fraction(self) -> float:
        """Fraction of beams that are not valid."""
        return float(1.0 - self.valid.mean())

    def points(self, dtype: type[np.floating[Any]] = np.float32) -> NDArray[np.floating[Any]]:
        """Cartesian points of the valid beams in the sensor frame, shape ``(M, 2)``.

        Computed once per dtype and cached; the array is read-only (copy it to modify it).
        """

        def make() -> NDArray[np.floating[Any]]:
            v = self.valid
            r = self.ranges[v].astype(dtype, copy=False)
            a = self.angles[v]
            out = np.empty((r.size, 2), dtype=dtype)
            out[:, 0] = r * np.cos(a)
            out[:, 1] = r * np.sin(a)
            return out

        return self._cached(f"points-{np.dtype(dtype).str}", make)

    def with_ranges(self, ranges: ArrayLike, stamp: float | None = None) -> LaserScan:
        """A copy with other ranges (and optionally another stamp), same geometry."""
        return LaserScan(
            stamp=self.stamp if stamp is None else stamp,
            ranges=np.asarray(ranges, dtype=np.float32),
            angle_min=self.angle_min,
            angle_increment=self.angle_increment,
            range_min=self.range_min,
            range_max=self.range_max,
        )

    def same_geometry(self, other: LaserScan, atol: float = 1e-9) -> bool:
        """True when both scans have the same beam layout and limits."""
        return (
            self.n_beams == other.n_beams
            and abs(self.angle_min - other.angle_min) <= atol
            and abs(self.angle_increment - other.angle_increment) <= atol
            and abs(self.range_min - other.range_min) <= 1e-6
            and abs(self.range_max - other.range_max) <= 1e-6
        )

    @classmethod
    def from_sensor(cls, sensor: SensorInfo, stamp: float, ranges: ArrayLike) -> LaserScan:
        """Build a scan with the geometry of ``sensor``."""
        return cls(
            stamp=stamp,
            ranges=np.asarray(ranges, dtype=np.float32),
            angle_min=sensor.angle_min,
            angle_increment=sensor.angle_increment,
            range_min=sensor.range_min,
            range_max=sensor.range_max,
        )


def _check_poses(name: str, poses: ArrayLike | None, n: int) -> NDArray[np.float64] | None:
    if poses is None:
        return None
    p = np.asarray(poses, dtype=np.float64)
    if p.shape != (n, 3):
        raise ScanError(f"{name} poses must have shape ({n}, 3) to match the scans, got {p.shape}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ScanError(
            f"{name} poses hold non-finite values ({int(bad.sum())} of {n}, first at scan {i}: "
            f"{p[i].tolist()})"
        )
    return p


@dataclass(eq=False)
class ScanSequence:
    """A recording: scans plus optional odometry and reference poses, all aligned to scans.

    ``odometry[i]`` and ``reference[i]`` are the robot poses ``(x, y, theta)`` at
    ``scans[i].stamp``; readers interpolate them to the scan stamps. They must be finite
    (`ScanError` otherwise), so no label or trajectory is ever computed from a NaN pose. The
    laser is assumed at the robot origin unless ``laser_offset`` says otherwise (pose of the
    laser in the robot frame).

    Attributes:
        name: Human-readable name (usually the file stem).
        scans: The scans, in time order.
        sensor: Sensor description (from the first scan unless given).
        odometry: Wheel odometry poses ``(N, 3)`` or None.
        reference: Reference (ground-truth or corrected) poses ``(N, 3)`` or None.
        reference_kind: Where the reference comes from (``"ground_truth"``, ``"corrected_log"``,
            ``"tum"``, ``"static"``...), or None.
        laser_offset: Pose of the laser in the robot frame.
        metadata: Free-form provenance (source path, topics, ...).
    """

    name: str
    scans: list[LaserScan]
    sensor: SensorInfo | None = None
    odometry: NDArray[np.float64] | None = None
    reference: NDArray[np.float64] | None = None
    reference_kind: str | None = None
    laser_offset: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.scans = list(self.scans)
        n = len(self.scans)
        self.odometry = _check_poses("odometry", self.odometry, n)
        self.reference = _check_poses("reference", self.reference, n)
        self.laser_offset = np.asarray(self.laser_offset, dtype=np.float64).reshape(3)
        if not np.isfinite(self.laser_offset).all():
            raise ScanError(f"laser offset {self.laser_offset.tolist()} is not finite")
        if self.sensor is None and n:
            s0 = self.scans[0]
            self.sensor = SensorInfo(
                name="unknown",
                n_beams=s0.n_beams,
                angle_min=s0.angle_min,
                angle_increment=s0.angle_increment,
                range_min=s0.range_min,
                range_max=s0.range_max,
                rate_hz=self.rate_hz,
            )

    def __len__(self) -> int:
        return len(self.scans)

    def __iter__(self) -> Iterator[LaserScan]:
        return iter(self.scans)

    def __getitem__(self, i: int) -> LaserScan:
        return self.scans[i]

    @property
    def stamps(self) -> NDArray[np.float64]:
        """Scan stamps (s), shape ``(N,)``."""
        return np.array([s.stamp for s in self.scans], dtype=np.float64)

    @property
    def duration(self) -> float:
        """Span of the scan stamps (s): latest minus earliest, so never negative.

        Equals last minus first for stamps in time order; stamps that run backwards (see
        `steps_back`) do not make it negative.
        """
        if len(self.scans) < 2:
            return 0.0
        stamps = self.stamps
        return float(stamps.max() - stamps.min())

    @property
    def steps_back(self) -> int:
        """Number of consecutive scan pairs whose stamp goes back in time."""
        return int((np.diff(self.stamps) < 0).sum()) if len(self.scans) > 1 else 0

    @property
    def rate_hz(self) -> float | None:
        """Median scan rate (Hz), or None with fewer than two scans."""
        if len(self.scans) < 2:
            return None
        dt = np.diff(self.stamps)
        dt = dt[dt > 0]
        return float(1.0 / np.median(dt)) if dt.size else None

    @property
    def beam_counts(self) -> NDArray[np.int64]:
        """Beams per scan."""
        return np.array([s.n_beams for s in self.scans], dtype=np.int64)

    @property
    def invalid_fraction(self) -> float:
        """Fraction of all beams that are invalid."""
        total = int(self.beam_counts.sum())
        if total == 0:
            return 0.0
        bad = sum(int((~s.valid).sum()) for s in self.scans)
        return bad / total

    def subsequence(self, indices: Sequence[int] | slice) -> ScanSequence:
        """A new sequence with the selected scans (and matching poses)."""
        idx = np.arange(len(self.scans))[indices]
        return ScanSequence(
            name=self.name,
            scans=[self.scans[i] for i in idx],
            sensor=self.sensor,
            odometry=None if self.odometry is None else self.odometry[idx],
            reference=None if self.reference is None else self.reference[idx],
            reference_kind=self.reference_kind,
            laser_offset=self.laser_offset.copy(),
            metadata=dict(self.metadata),
        )

    def ranges_matrix(self) -> NDArray[np.float32]:
        """All ranges as ``(N, n_beams)``; raises if beam counts differ."""
        counts = set(self.beam_counts.tolist())
        if len(counts) != 1:
            raise ScanError(f"sequence {self.name!r} mixes beam counts {sorted(counts)}")
        return np.stack([s.ranges for s in self.scans])
