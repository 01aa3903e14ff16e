"""The fused motion model: wheels, the judged scan match and a prediction, by their information.

At every scan up to three estimates of the robot's motion since the previous scan exist:

* the **wheel increment**, when the recording has odometry. Its covariance comes from a noise
  model of *this* robot, fitted on this recording as the run goes (`WheelNoise`): GMapping's
  odometry model (``srr``, ``srt``, ``str``, ``stt``, plus floors) with one scale per axis,
  the robust (median-based) scale of the wheels' disagreement with accepted, well-conditioned
  matches. No reference is read.
* the **scan-to-scan match**, when the judge calls it normal. Its information is the match's
  own point-to-line Hessian (`scanguard.matching.result.MatchResult.hessian`), normalised by
  the inlier count and divided by ``match_sigma ** 2``: a direction the scan does not constrain
  (along a corridor) carries no weight there, so the wheels decide it.
* a **constant-velocity prediction** (the last fused increment, scaled by the time step): a
  weak prior that keeps the fusion defined when nothing else is there.

Verdicts act on the sources: a faulty (rejected) match loses its term; a well-conditioned
normal match that disagrees with the wheels far beyond their fitted noise (squared Mahalanobis
distance above ``wheel_flag_chi2``) **flags the wheels** for that step (wheel slip, or wheels
that report forward motion while the robot backs up), and the wheels lose their term.

The fused increment is the information-weighted mean of the remaining terms (angles taken
relative to one of them, so that wrapping never averages +pi and -pi to 0), and its covariance
is the inverse of the summed information. `FusedMotion.step` returns both, with which sources
were used and why (`MotionStep.sources`, a row of ``decisions.csv``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, field_validator

from scanguard.config import YamlModel
from scanguard.geometry import wrap_angle
from scanguard.slam.gmapping.motion import motion_sigma
from scanguard.slam.grid import sensor_to_robot_increment

#: Step of the finite differences that carry the match's information into the robot frame.
_DIFF_STEP = 1e-6
#: Median of |N(0, 1)|: a median of absolute normalised residuals over this is a sigma.
_HALF_NORMAL_MEDIAN = 0.6744897501960817


class FusionConfig(YamlModel):
    """Settings of the fused motion model (`FusedMotion`).

    Attributes:
        match_sigma: Standard deviation (m) of a match's translation along a direction whose
            normalised information (``hessian / n_inliers``) is 1; rotation scales with the
            scan's extent through the Hessian.
        match_min_inliers: A match with fewer inlier pairs brings no information.
        match_weight_by_fault: Scale an accepted match's information by ``1 - p_fault`` (the
            CNN's fault probability); off: full weight.
        srr: Base wheel noise, translation from translation (GMapping's name).
        srt: Base wheel noise, rotation from translation.
        str: Base wheel noise, translation from rotation.
        stt: Base wheel noise, rotation from rotation.
        wheel_floor_xy: Floor of the wheel translation sigma per step (m).
        wheel_floor_theta: Floor of the wheel rotation sigma per step (rad).
        fit_window: Steps in the robust fit of the wheel noise (the most recent ones).
        fit_min: Steps needed before the fitted scales replace the base model.
        fit_min_eig: A match enters the fit, and may flag the wheels, only when its smallest
            normalised Hessian eigenvalue (``eig_min / n_inliers``) is at least this.
        noise_fit: How the recording fits the noise: ``wheels`` scales the wheel model alone by
            its disagreement with accepted matches (the match keeps ``match_sigma``);
            ``three_cornered`` fits both, per axis, from the three pairwise disagreements of
            wheels, match and prediction (`ThreeCorneredHat`): where the matches are worse
            than ``match_sigma`` says (a crowd, a scanner of few beams), they lose weight, and
            where the wheels are better than GMapping's model, they gain it. Without
            odometry only two sources remain and nothing is fitted.
        wheel_flag_chi2: Squared Mahalanobis distance between wheels and a well-conditioned
            normal match beyond which the wheels are flagged for that step (None: never).
            The default is the 99 % quantile of chi-square with three degrees of freedom,
            chosen leave one log out over 25 (p = 1.6e-5), 16.27 (99.9 %) and 11.34 on the
            Freiburg logs (README): wheels slipping by 5 cm a step against a corridor match
            measure 8-22, agreeing steps under 2.
        vouch_chi2: A match the judge rejected keeps its term where the wheels vouch for it:
            the match is well-conditioned, the wheels have been fitted (``fit_min`` steps)
            and are not distrusted, and the two agree within this squared Mahalanobis
            distance. Two independent sensors that agree within the wheels' fitted noise
            measured the same motion, so leaving the match out only puts the wheels'
            systematic error (scale, turn) in its place. The match still counts as
            rejected, never fits the wheel noise and never flags the wheels. None: off.
        doubted_weight: A match the judge rejected (and the wheels did not vouch for) keeps
            its term with its information scaled by ``(1 - p)^2``, ``p`` its fault probability:
            its standard deviation grows as ``1 / (1 - p)``, so a match just over the
            threshold keeps most of its say and a sure fault none. It never fits the wheel
            noise or flags the wheels. Only where there are wheels: without odometry a
            rejected match leaves the constant-velocity prediction alone. Off: a rejected
            match loses its term.
        wheel_flag_hold: After the wheels were flagged, they stay distrusted for up to this
            many steps in which no well-conditioned normal match can test them (a rejected or
            degenerate match): wheels that lie tend to lie for a while (0: no hold).
        seed_match: What seeds the scan matcher: ``wheels`` (the wheel increment, else the
            constant-velocity prediction of the main instance where the recording has no
            odometry), ``prediction`` (always the prediction) or ``none`` (the identity, as the
            paper starts ICP). A point-to-line match started from the identity stops short
            where the scan barely constrains the motion (along a corridor: ACES's matches
            covered 295 m of the wheels' 324 m), and the fusion then reads that bias as
            information; started from the wheels, the same matches carry the wheels' estimate
            along the corridor and their own across it. ``true``/``false`` (older configs)
            read as ``prediction``/``none``.
        prediction_sigma_xy: Sigma of the constant-velocity prediction per step (m).
        prediction_sigma_theta: Sigma of the constant-velocity prediction per step (rad).
    """

    match_sigma: float = Field(default=0.005, gt=0.0, le=10.0)
    match_min_inliers: int = Field(default=20, ge=3)
    match_weight_by_fault: bool = False
    srr: float = Field(default=0.1, ge=0.0, le=10.0)
    srt: float = Field(default=0.2, ge=0.0, le=10.0)
    str: float = Field(default=0.1, ge=0.0, le=10.0)
    stt: float = Field(default=0.2, ge=0.0, le=10.0)
    wheel_floor_xy: float = Field(default=0.002, gt=0.0, le=10.0)
    wheel_floor_theta: float = Field(default=0.002, gt=0.0, le=10.0)
    fit_window: int = Field(default=400, ge=10, le=100_000)
    fit_min: int = Field(default=50, ge=5)
    fit_min_eig: float = Field(default=0.1, ge=0.0)
    noise_fit: Literal["wheels", "three_cornered"] = "wheels"
    wheel_flag_chi2: float | None = Field(default=11.345, gt=0.0)
    wheel_flag_hold: int = Field(default=0, ge=0, le=100_000)
    vouch_chi2: float | None = Field(default=None, gt=0.0)
    doubted_weight: bool = False
    seed_match: Literal["wheels", "prediction", "none"] = "wheels"
    prediction_sigma_xy: float = Field(default=0.25, gt=0.0, le=1e3)
    prediction_sigma_theta: float = Field(default=0.25, gt=0.0, le=1e3)

    @field_validator("seed_match", mode="before")
    @classmethod
    def _seed_from_bool(cls, value: object) -> object:
        if isinstance(value, bool):  # the former switch: the prediction, or nothing
            return "prediction" if value else "none"
        return value


@dataclass(frozen=True)
class MotionStep:
    """The fused motion of one step.

    Attributes:
        increment: Fused robot-frame increment ``(dx, dy, dtheta)``.
        covariance: Its covariance ``(3, 3)`` (inverse of the summed information).
        sources: The terms used, ``+``-joined: ``wheels``, ``match``, ``vouched_match`` (a
            rejected match the wheels vouched for, ``FusionConfig.vouch_chi2``),
            ``prediction``.
        wheels_flagged: The wheels disagreed with a well-conditioned normal match beyond
            their fitted noise and were left out.
        mahalanobis2: Squared Mahalanobis distance of wheels against the match (NaN when
            not both were there).
    """

    increment: NDArray[np.float64]
    covariance: NDArray[np.float64]
    sources: str
    wheels_flagged: bool
    mahalanobis2: float


class WheelNoise:
    """This robot's wheel noise, fitted as the run goes (see the module docstring).

    Args:
        config: The fusion settings (base model, floors, window).
    """

    def __init__(self, config: FusionConfig) -> None:
        self.config = config
        self._ratios = _Rows(config.fit_window, 3)
        self.scale = np.ones(3)

    def base_sigma(self, wheel: NDArray[np.float64]) -> NDArray[np.float64]:
        """Sigmas ``(x, y, theta)`` of the base model for one wheel increment."""
        c = self.config
        s = motion_sigma(wheel, c.srr, c.srt, c.str, c.stt)
        return np.asarray(s + np.array([c.wheel_floor_xy, c.wheel_floor_xy, c.wheel_floor_theta]))

    def sigma(self, wheel: NDArray[np.float64]) -> NDArray[np.float64]:
        """Fitted sigmas ``(x, y, theta)`` of one wheel increment."""
        return self.scale * self.base_sigma(wheel)

    def observe(self, wheel: NDArray[np.float64], match: NDArray[np.float64]) -> None:
        """Add one step where a well-conditioned normal match measured the true motion."""
        e = wheel - match
        e[2] = wrap_angle(e[2])
        self._ratios.append(np.abs(e) / self.base_sigma(wheel))
        if len(self._ratios) >= self.config.fit_min:
            med = np.median(self._ratios.rows(), axis=0) / _HALF_NORMAL_MEDIAN
            # a scale may shrink the base model tenfold or widen it a hundredfold; beyond that
            # the fit is more likely wrong (a stationary robot) than the model
            self.scale = np.clip(med, 0.1, 100.0)

    @property
    def n_fitted(self) -> int:
        """Steps in the fit."""
        return len(self._ratios)


class _Rows:
    """The last ``maxlen`` rows appended, in a ring (a per-column median ignores their order).

    A deque of small arrays cost a stack of up to ``maxlen`` rows at every step (the
    largest part of the per-scan fusion); the ring's rows are already one array.
    """

    def __init__(self, maxlen: int, width: int) -> None:
        self._buf = np.empty((maxlen, width))
        self._n = 0
        self._next = 0

    def append(self, row: NDArray[np.float64]) -> None:
        self._buf[self._next] = row
        self._next = (self._next + 1) % len(self._buf)
        self._n = min(self._n + 1, len(self._buf))

    def rows(self) -> NDArray[np.float64]:
        """The rows held, in no particular order."""
        return self._buf[: self._n]

    def __len__(self) -> int:
        return self._n


class ThreeCorneredHat:
    """Per-axis noise of the wheels and of the match, fitted from their disagreements.

    Three estimates of the same motion with independent errors (the wheels, the match and the
    constant-velocity prediction, whose error is the robot's change of velocity) give three
    pairwise differences whose variances are sums of two: ``v_mw = s_m + s_w``,
    ``v_mp = s_m + s_p``, ``v_wp = s_w + s_p``. Solved, ``s_m = (v_mw + v_mp - v_wp) / 2`` and
    ``s_w = (v_mw + v_wp - v_mp) / 2`` (the three-cornered hat of clock metrology). Each
    variance is robust: ``(median |e| / 0.6745) ** 2`` over the most recent steps, so that
    the rare failed match or slipping wheel does not widen the fit. The match's fitted
    variance is compared with the median variance its Hessian information claims, and the
    wheels' with the median variance of GMapping's model: their ratios scale the two terms.

    Args:
        config: The fusion settings (window, minimum steps).
    """

    def __init__(self, config: FusionConfig) -> None:
        self.config = config
        self._rows = _Rows(config.fit_window, 15)
        #: Variance multiplier per axis of the match covariance (1: as its Hessian says).
        self.match_scale = np.ones(3)
        #: Sigma multiplier per axis of the wheel model (as `WheelNoise.scale`).
        self.wheel_scale = np.ones(3)

    def observe(
        self,
        wheel: NDArray[np.float64],
        match: NDArray[np.float64],
        prediction: NDArray[np.float64],
        match_variance: NDArray[np.float64],
        wheel_variance: NDArray[np.float64],
    ) -> None:
        """Add one step with all three estimates (and the variances the two models claim)."""
        diffs = [match - wheel, match - prediction, wheel - prediction]
        for d in diffs:
            d[2] = wrap_angle(d[2])
        self._rows.append(np.concatenate([*diffs, match_variance, wheel_variance]))
        if len(self._rows) < self.config.fit_min:
            return
        med = np.median(np.abs(self._rows.rows()), axis=0)
        v_mw, v_mp, v_wp = ((med[:9] / _HALF_NORMAL_MEDIAN) ** 2).reshape(3, 3)
        claimed_m, claimed_w = med[9:12], med[12:15]
        # a negative solution means that source is far better than the other two can resolve:
        # floor it at 1 % of the smallest pairwise variance rather than at zero
        floor = 0.01 * np.minimum(np.minimum(v_mw, v_mp), v_wp) + 1e-18
        s_m = np.maximum(0.5 * (v_mw + v_mp - v_wp), floor)
        s_w = np.maximum(0.5 * (v_mw + v_wp - v_mp), floor)
        # the same bounds as the wheel fit: a sigma shrunk tenfold or widened a hundredfold
        self.match_scale = np.clip(s_m / np.maximum(claimed_m, 1e-18), 0.01, 1e4)
        self.wheel_scale = np.clip(np.sqrt(s_w / np.maximum(claimed_w, 1e-18)), 0.1, 100.0)

    @property
    def n_fitted(self) -> int:
        """Steps in the fit."""
        return len(self._rows)


def match_information(
    hessian: ArrayLike, n_inliers: int, sensor_increment: ArrayLike, laser_offset: ArrayLike,
    match_sigma: float,
) -> NDArray[np.float64]:  # fmt: skip
    """Information ``(3, 3)`` of a match's robot-frame increment.

    The Hessian is in the previous sensor frame's ``(x, y, theta)``; the robot-frame increment
    is ``offset (+) s (+) offset^-1``, whose Jacobian in ``s`` (finite differences: exact to
    ~1e-9 for these smooth maps) carries the information over: ``J^-T (H / n / sigma^2) J^-1``.
    """
    h = np.asarray(hessian, dtype=np.float64) / max(int(n_inliers), 1) / match_sigma**2
    s = np.asarray(sensor_increment, dtype=np.float64).reshape(3)
    probes = np.vstack([s + _DIFF_STEP * np.eye(3), s - _DIFF_STEP * np.eye(3)])
    r = sensor_to_robot_increment(probes, laser_offset)
    jac = (r[:3] - r[3:]).T / (2.0 * _DIFF_STEP)
    jac[2] = np.array([0.0, 0.0, 1.0])  # the rotation passes through unchanged
    inv = np.linalg.inv(jac)
    # a ridge of 1e-9 (a sigma of ~3e4 m or rad) keeps a fully degenerate match invertible
    return np.asarray(inv.T @ h @ inv) + 1e-9 * np.eye(3)


class FusedMotion:
    """The fused motion of one back-end instance (see the module docstring).

    Args:
        config: Fusion settings.
        flag_wheels: Let a normal match flag the wheels (False for the unguarded comparison).
    """

    def __init__(self, config: FusionConfig | None = None, *, flag_wheels: bool = True) -> None:
        self.config = config or FusionConfig()
        self.flag_wheels = flag_wheels
        self.wheels = WheelNoise(self.config)
        three = self.config.noise_fit == "three_cornered"
        self.hat = ThreeCorneredHat(self.config) if three else None
        self._last = np.zeros(3)
        self._last_dt = 0.0
        self._since_flag = math.inf
        self.counts = {
            "match": 0,
            "vouched_match": 0,
            "doubted_match": 0,
            "wheels": 0,
            "flagged": 0,
            "prediction_only": 0,
        }

    def prediction(self, dt: float) -> NDArray[np.float64]:
        """The constant-velocity prediction of the next increment, ``dt`` seconds on."""
        return self._prediction(dt)[0]

    def _prediction(self, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        c = self.config
        ratio = dt / self._last_dt if self._last_dt > 0.0 and dt > 0.0 else 1.0
        pred = self._last * min(ratio, 5.0)
        sig = np.array([c.prediction_sigma_xy, c.prediction_sigma_xy, c.prediction_sigma_theta])
        return pred, np.diag(1.0 / sig**2)

    def step(
        self,
        dt: float,
        wheel: NDArray[np.float64] | None,
        match: NDArray[np.float64] | None,
        match_info: NDArray[np.float64] | None,
        *,
        eig_min_per_inlier: float = math.nan,
        fault_probability: float = math.nan,
        rejected: bool = False,
    ) -> MotionStep:
        """Fuse one step.

        Args:
            dt: Seconds since the previous scan.
            wheel: Robot-frame wheel increment, or None (no odometry).
            match: Robot-frame increment of the match, or None (failed or not computed).
            match_info: Its information `match_information` (with ``match``).
            eig_min_per_inlier: The match's smallest normalised Hessian eigenvalue.
            fault_probability: The CNN's fault probability of the match (NaN: not asked).
            rejected: The gate rejected the match: it loses its term unless the wheels vouch
                for it (``FusionConfig.vouch_chi2``).

        Returns:
            The fused step.
        """
        c = self.config
        pred, info_p = self._prediction(dt)
        terms: list[tuple[str, NDArray[np.float64], NDArray[np.float64]]] = []
        flagged, d2 = False, math.nan
        info_w = None
        if wheel is not None:
            info_w = np.diag(1.0 / self.wheels.sigma(wheel) ** 2)
        if match is not None and match_info is not None and rejected:
            if c.vouch_chi2 is not None:
                info_m = self._scaled_match_information(match_info)
                d2 = self._vouch(wheel, match, info_w, info_m, eig_min_per_inlier)
                if d2 <= c.vouch_chi2:
                    terms.append(("vouched_match", match, info_m))
            vouched = bool(terms)
            # only beside the wheels: without them a faulty match leaves the prediction alone
            if c.doubted_weight and wheel is not None and not vouched:
                # its sigma grows as 1 / (1 - p): just over the threshold it keeps weight
                w = max(1.0 - fault_probability, 0.0) ** 2
                if w > 0.0:  # NaN (no probability: another gate) never compares true
                    info_m = self._scaled_match_information(match_info) * w
                    terms.append(("doubted_match", match, info_m))
        elif match is not None and match_info is not None:
            info_m = self._scaled_match_information(match_info)
            if c.match_weight_by_fault and math.isfinite(fault_probability):
                info_m = info_m * max(1.0 - fault_probability, 0.0)
            well = eig_min_per_inlier >= c.fit_min_eig
            if wheel is not None and info_w is not None and well:
                d2 = _mahalanobis2(wheel, match, info_w, info_m)
                if self.flag_wheels and c.wheel_flag_chi2 is not None and d2 > c.wheel_flag_chi2:
                    flagged, self._since_flag = True, 0.0
                else:
                    self._observe(wheel, match, pred, match_info)
                    self._since_flag = math.inf  # tested and found right
            terms.append(("match", match, info_m))
        if not flagged and wheel is not None and self._since_flag < c.wheel_flag_hold:
            # untested this step, and lying a moment ago: still distrusted
            self._since_flag += 1.0
            flagged = True
        if wheel is not None and info_w is not None and not flagged:
            terms.append(("wheels", wheel, info_w))
        terms.append(("prediction", pred, info_p))
        inc, cov = _fuse(terms)
        self._last, self._last_dt = inc, dt
        self._count(terms, flagged)
        names = "+".join(t[0] for t in terms)
        return MotionStep(inc, cov, names, flagged, d2)

    def _vouch(
        self,
        wheel: NDArray[np.float64] | None,
        match: NDArray[np.float64],
        info_w: NDArray[np.float64] | None,
        info_m: NDArray[np.float64],
        eig_min_per_inlier: float,
    ) -> float:
        """Squared Mahalanobis distance of a rejected match to the wheels (NaN: no vouch).

        Only wheels that can vouch get a distance: fitted on this recording, not distrusted
        (flagged, or held after a flag), against a well-conditioned match (a degenerate one
        would agree along the direction it cannot measure).
        """
        c = self.config
        if (
            wheel is None
            or info_w is None
            or self.wheels.n_fitted < c.fit_min
            or self._since_flag < math.inf
            or not eig_min_per_inlier >= c.fit_min_eig
        ):
            return math.nan
        return _mahalanobis2(wheel, match, info_w, info_m)

    def _scaled_match_information(self, info: NDArray[np.float64]) -> NDArray[np.float64]:
        """The match's information with the fitted per-axis variance scales applied."""
        if self.hat is None:
            return info
        d = 1.0 / np.sqrt(self.hat.match_scale)
        return np.asarray(info * np.outer(d, d))

    def _observe(
        self,
        wheel: NDArray[np.float64],
        match: NDArray[np.float64],
        prediction: NDArray[np.float64],
        match_info: NDArray[np.float64],
    ) -> None:
        """One step where a well-conditioned normal match agreed with the wheels: fit."""
        if self.hat is None:
            self.wheels.observe(wheel, match)
            return
        claimed_m = np.diag(np.linalg.inv(match_info))
        claimed_w = self.wheels.base_sigma(wheel) ** 2
        self.hat.observe(wheel, match, prediction, claimed_m, claimed_w)
        self.wheels.scale = self.hat.wheel_scale

    def _count(self, terms: list[tuple[str, NDArray[np.float64], NDArray[np.float64]]],
               flagged: bool) -> None:  # fmt: skip
        used = {t[0] for t in terms}
        self.counts["match"] += "match" in used
        self.counts["vouched_match"] += "vouched_match" in used
        self.counts["doubted_match"] += "doubted_match" in used
        self.counts["wheels"] += "wheels" in used
        self.counts["flagged"] += flagged
        self.counts["prediction_only"] += used == {"prediction"}


def _mahalanobis2(
    wheel: NDArray[np.float64],
    match: NDArray[np.float64],
    info_w: NDArray[np.float64],
    info_m: NDArray[np.float64],
) -> float:
    """Squared Mahalanobis distance between the wheel and match increments."""
    e = wheel - match
    e[2] = wrap_angle(e[2])
    cov = np.linalg.inv(info_w) + np.linalg.inv(info_m)
    return float(e @ np.linalg.solve(cov, e))


def _fuse(
    terms: list[tuple[str, NDArray[np.float64], NDArray[np.float64]]],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Information-weighted mean and covariance of ``(name, increment, information)`` terms."""
    ref = terms[0][1]
    total = np.zeros((3, 3))
    vec = np.zeros(3)
    for _, x, info in terms:
        d = x - ref
        d[2] = wrap_angle(d[2])
        total += info
        vec += info @ d
    cov = np.linalg.inv(total)
    inc = ref + cov @ vec
    inc[2] = wrap_angle(inc[2])
    return inc, 0.5 * (cov + cov.T)
