"""`scanguard.slam.graph.odometry`: the fused steps' covariance compounded between nodes."""

from __future__ import annotations

import numpy as np
import pytest

from scanguard.geometry import compose, inverse, relative, wrap_angle
from scanguard.slam.graph.odometry import StepCovariance, pose2_adjoint

SIG = np.diag([0.02**2, 0.01**2, 0.03**2])


def test_two_straight_steps_known_answer() -> None:
    acc = StepCovariance(np.zeros(3))
    acc.add(np.array([1.0, 0.0, 0.0]), SIG)
    np.testing.assert_allclose(acc.sensor_covariance(), SIG, atol=1e-15)
    acc.add(np.array([1.0, 0.0, 0.0]), SIG)
    sx, sy, st = 0.02**2, 0.01**2, 0.03**2
    # the first step's heading error swings the second metre sideways
    want = np.array([[2 * sx, 0.0, 0.0], [0.0, 2 * sy + st, st], [0.0, st, 2 * st]])
    np.testing.assert_allclose(acc.sensor_covariance(), want, atol=1e-15)
    acc.reset()
    np.testing.assert_allclose(acc.sensor_covariance(), np.zeros((3, 3)))


def test_unknown_step_makes_the_increment_unknown() -> None:
    acc = StepCovariance(np.zeros(3))
    acc.add(np.array([0.1, 0.0, 0.0]), SIG)
    acc.add(np.array([0.1, 0.0, 0.0]), None)
    assert acc.sensor_covariance() is None
    acc.add(np.array([0.1, 0.0, 0.0]), SIG)
    assert acc.sensor_covariance() is None
    acc.reset()
    acc.add(np.array([0.1, 0.0, 0.0]), np.full((3, 3), np.nan))
    assert acc.sensor_covariance() is None


def test_adjoint_matches_conjugation() -> None:
    t = np.array([0.3, -0.2, 0.7])
    d = np.array([1e-6, -2e-6, 3e-6])
    lhs = compose(compose(t, d), inverse(t))
    np.testing.assert_allclose(lhs, pose2_adjoint(t) @ d, atol=1e-11)


@pytest.mark.parametrize("offset", [np.zeros(3), np.array([0.25, 0.05, 0.1])])
def test_monte_carlo_agrees(offset: np.ndarray) -> None:
    """Sampled noisy steps, composed, give the covariance the compounding predicts."""
    rng = np.random.default_rng(5)
    steps = [np.array([0.05, 0.01, 0.04]), np.array([0.04, -0.01, 0.08]), np.array([0.06, 0, 0])]
    covs = [np.diag([4e-4, 1e-4, 4e-4]), np.diag([1e-4, 1e-4, 9e-4]), SIG]
    acc = StepCovariance(offset)
    for u, c in zip(steps, covs, strict=True):
        acc.add(u, c)
    want = acc.sensor_covariance()
    assert want is not None
    n = 40000
    sensor_true = compose(compose(inverse(offset), _chain(steps)), offset)
    errs = np.empty((n, 3))
    for i in range(n):
        noisy = [
            u + rng.multivariate_normal(np.zeros(3), c) for u, c in zip(steps, covs, strict=True)
        ]
        sensor = compose(compose(inverse(offset), _chain(noisy)), offset)
        d = relative(sensor_true, sensor)  # right perturbation, as gtsam's between factor
        d[2] = wrap_angle(d[2])
        errs[i] = d
    got = np.cov(errs.T)
    np.testing.assert_allclose(got, want, rtol=0.06, atol=2e-6)


def _chain(steps: list[np.ndarray]) -> np.ndarray:
    pose = np.zeros(3)
    for u in steps:
        pose = compose(pose, u)
    return pose
