"""Domain randomisation of simulated sequences: draw a sensing domain, simulate it, thin it.

A `DomainRandomization` (an environment's ``randomize``) turns into one `DomainDraw` per
sequence. The draw is seeded by the randomisation's seed, the environment's seed and the
sequence index only, so it is the same in every build, worker and resume. It is applied as
overrides of the simulator's sensor and scan rate (`DomainDraw.overrides`), and thinned
sequences are reduced after the simulation (`thin_indices`), as CARMEN logs were recorded:
a scan is kept once the robot travelled about ``d`` metres or turned about ``a`` since the
last kept scan.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.dataset.config import DomainRandomization
from scanguard.geometry import wrap_angle
from scanguard.scan import ScanSequence

log = logging.getLogger(__name__)

#: Salt of the draw's seed, so that it never shares a stream with the simulator (which seeds
#: ``default_rng([seed, component])``).
_SALT = 0x646F6D72  # "domr"


@dataclass(frozen=True)
class DomainDraw:
    """The sensing domain drawn for one sequence.

    Attributes:
        n_beams: Beams per scan.
        fov_deg: Field of view (deg).
        range_max: Maximum range (m).
        rate_hz: Rate (Hz) of the simulated scanner (before thinning).
        noise_std: Constant range noise std (m).
        noise_rel: Range-proportional range noise std.
        dropout_prob: Probability that a beam returns nothing.
        thinned: Whether the sequence is thinned (CARMEN style).
        thin_distance: Distance (m) between kept scans; None unless thinned.
        thin_angle_deg: Rotation (deg) between kept scans; None unless thinned.
    """

    n_beams: int
    fov_deg: float
    range_max: float
    rate_hz: float
    noise_std: float
    noise_rel: float
    dropout_prob: float
    thinned: bool
    thin_distance: float | None = None
    thin_angle_deg: float | None = None

    def overrides(self) -> dict[str, Any]:
        """Overrides for `scanguard.sim.simulate`.

        Nested keys (``sensor__n_beams``), so that a ``sensor`` dict in the environment's
        overrides is merged with, not replaced by, the draw.
        """
        return {
            "stride": 1,  # the drawn rate is the rate of the matched scans
            "scan_rate_hz": self.rate_hz,
            "sensor__n_beams": self.n_beams,
            "sensor__fov_deg": self.fov_deg,
            "sensor__range_max": self.range_max,
            "sensor__rate_hz": self.rate_hz,
            "sensor__noise_std": self.noise_std,
            "sensor__noise_rel": self.noise_rel,
            "sensor__dropout_prob": self.dropout_prob,
        }

    def as_dict(self) -> dict[str, Any]:
        """The draw as JSON-ready values (stored in the sequence file's meta)."""
        return asdict(self)


def _uniform(rng: np.random.Generator, pair: tuple[float, float]) -> float:
    lo, hi = float(pair[0]), float(pair[1])
    return lo if hi <= lo else float(rng.uniform(lo, hi))


def _log_uniform(rng: np.random.Generator, pair: tuple[float, float]) -> float:
    lo, hi = float(pair[0]), float(pair[1])
    if hi <= lo:
        return lo
    # log-uniform: as many sequences between 1 and 6 Hz as between 6 and 40 Hz
    return float(min(hi, max(lo, math.exp(rng.uniform(math.log(lo), math.log(hi))))))


def draw_seed(spec: DomainRandomization, env_seed: int, index: int) -> list[int]:
    """The seed entropy of sequence ``index`` of an environment (no ``hash()``: stable)."""
    mask = 2**64 - 1  # SeedSequence takes non-negative integers; env seeds may be negative
    return [_SALT, int(spec.seed) & mask, int(env_seed) & mask, int(index) & mask]


def draw_domain(spec: DomainRandomization, env_seed: int, index: int) -> DomainDraw:
    """Draw the sensing domain of sequence ``index`` of an environment.

    Every value is drawn in a fixed order from one generator, so the same arguments always
    give the same draw, and every value lies in its ``spec`` range.

    Args:
        spec: The ranges.
        env_seed: The environment's ``seed``.
        index: The sequence index within the environment.

    Returns:
        The draw.
    """
    rng = np.random.default_rng(draw_seed(spec, env_seed, index))
    n_lo, n_hi = spec.n_beams
    n_beams = int(rng.integers(n_lo, n_hi, endpoint=True))
    fov = _uniform(rng, spec.fov_deg)
    range_max = _log_uniform(rng, spec.range_max)
    noise_std = _uniform(rng, spec.noise_std)
    noise_rel = _uniform(rng, spec.noise_rel)
    dropout = _uniform(rng, spec.dropout_prob)
    # always drawn (used or not), so that thinned_fraction does not shift the other values
    u_thin = float(rng.random())
    rate = _log_uniform(rng, spec.rate_hz)
    thin_rate = _log_uniform(rng, spec.thin_rate_hz)
    thin_d = _uniform(rng, spec.thin_distance)
    thin_a = _uniform(rng, spec.thin_angle_deg)
    thinned = u_thin < spec.thinned_fraction
    return DomainDraw(
        n_beams=n_beams,
        fov_deg=fov,
        range_max=range_max,
        rate_hz=thin_rate if thinned else rate,
        noise_std=noise_std,
        noise_rel=noise_rel,
        dropout_prob=dropout,
        thinned=thinned,
        thin_distance=thin_d if thinned else None,
        thin_angle_deg=thin_a if thinned else None,
    )


def simulated_duration(
    draw: DomainDraw, spec: DomainRandomization, duration: float, scan_stride: int = 1
) -> float:
    """Seconds to simulate so that an unthinned sequence has at most ``spec.max_pairs`` pairs.

    Thinned sequences are simulated for the whole ``duration`` (their pair count depends on
    the distance travelled; `randomized_sequence` cuts them).
    """
    if draw.thinned:
        return float(duration)
    return float(min(duration, spec.max_pairs * scan_stride / draw.rate_hz))


def thin_indices(
    poses: NDArray[np.float64], distance: float, angle_rad: float
) -> NDArray[np.int64]:
    """Indices of the scans kept by CARMEN-style thinning.

    The first scan is kept; each later scan is kept when the robot moved at least
    ``distance`` metres or turned at least ``angle_rad`` since the last kept one.

    Args:
        poses: ``(N, 3)`` robot poses (reference).
        distance: Distance threshold (m).
        angle_rad: Rotation threshold (rad).

    Returns:
        Increasing indices, starting with 0 (empty for no poses).
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    keep = [0]
    last = p[0]
    for i in range(1, p.shape[0]):
        moved = math.hypot(p[i, 0] - last[0], p[i, 1] - last[1])
        turned = abs(float(wrap_angle(p[i, 2] - last[2])))
        if moved >= distance or turned >= angle_rad:
            keep.append(i)
            last = p[i]
    return np.asarray(keep, dtype=np.int64)


def randomized_sequence(
    seq: ScanSequence, draw: DomainDraw, spec: DomainRandomization
) -> tuple[ScanSequence, dict[str, Any]]:
    """Thin (when drawn) and cut a simulated sequence; its record for the file's meta.

    Args:
        seq: The simulated sequence (with reference poses), after the environment's
            ``scan_stride``.
        draw: Its draw.
        spec: The ranges (for ``max_pairs``).

    Returns:
        The sequence to label and ``{**draw, "scans", "pairs", "simulated_scans", "cut"}``.
    """
    n_sim = len(seq)
    if draw.thinned and seq.reference is not None and n_sim > 1:
        assert draw.thin_distance is not None and draw.thin_angle_deg is not None
        idx = thin_indices(seq.reference, draw.thin_distance, math.radians(draw.thin_angle_deg))
        if idx.size < 2:
            # the robot barely moved: keep the last scan too rather than fail the build
            log.warning(
                "sequence %r: the robot never moved %.2f m or turned %.1f deg; keeping the "
                "first and last scan",
                seq.name,
                draw.thin_distance,
                draw.thin_angle_deg,
            )
            idx = np.asarray([0, n_sim - 1], dtype=np.int64)
        seq = seq.subsequence(idx.tolist())
    cut = len(seq) > spec.max_pairs + 1
    if cut:
        seq = seq.subsequence(slice(0, spec.max_pairs + 1))
    record = {
        **draw.as_dict(),
        "simulated_scans": n_sim,
        "scans": len(seq),
        "pairs": max(len(seq) - 1, 0),
        "cut": cut,
    }
    seq.metadata["domain"] = record
    return seq, record
