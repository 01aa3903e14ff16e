"""ICP from several starts against one target: each result is that of a match of its own."""

from __future__ import annotations

import numpy as np
import pytest

from scanguard.geometry import inverse, transform_points
from scanguard.matching.config import ICPConfig
from scanguard.matching.icp import icp_point_to_line, icp_point_to_point, match, match_starts


def _same(a, b) -> None:
    assert np.array_equal(a.pose, b.pose)
    assert a.iterations == b.iterations
    assert a.converged == b.converged
    assert a.reason == b.reason
    assert np.array_equal(
        np.asarray([a.mean_residual, a.median_residual]),
        np.asarray([b.mean_residual, b.median_residual]),
        equal_nan=True,
    )
    assert a.n_inliers == b.n_inliers
    if a.hessian is not None or b.hessian is not None:
        assert np.array_equal(a.hessian, b.hessian)


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, 300)
    walls = np.vstack(
        [
            np.column_stack([-2 + 4 * t, np.full_like(t, -1.5)]),
            np.column_stack([np.full_like(t, 2.0), -1.5 + 3 * t]),
            np.column_stack([-2 + 2 * t, np.full_like(t, 1.5)]),
            np.column_stack([np.full_like(t, -2.0), -1.5 + 2 * t]),
        ]
    )
    target = walls + rng.normal(0.0, 0.005, walls.shape)
    true = np.array([0.12, -0.07, 0.05])
    source = transform_points(inverse(true), walls[::3]) + rng.normal(0.0, 0.005, (400, 2))
    return source, target


@pytest.mark.parametrize("method", ["point_to_line", "point_to_point"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_starts_equal_separate_matches(method, seed):
    source, target = _scene(seed)
    starts = [np.zeros(3), np.array([0.1, -0.05, 0.04]), np.array([0.3, 0.2, -0.1]), None]
    cfg = ICPConfig(max_correspondence_distance=0.3)
    together = match_starts(method, source, target, starts, cfg)
    assert len(together) == len(starts)
    for start, result in zip(starts, together, strict=True):
        _same(result, match(method, source, target, start, cfg))
    one = icp_point_to_line if method == "point_to_line" else icp_point_to_point
    _same(together[1], one(source, target, starts[1], cfg))


def test_starts_keep_failures_in_place():
    source, target = _scene(3)
    starts = [np.array([np.nan, 0.0, 0.0]), np.zeros(3)]
    a, b = match_starts("point_to_line", source, target, starts)
    assert not a.converged and a.reason == "non-finite initial guess"
    _same(b, match("point_to_line", source, target, np.zeros(3)))
    few = match_starts("point_to_line", source[:2], target, [np.zeros(3), np.zeros(3)])
    assert all(not r.converged for r in few)
