"""Search lanes: a branch-and-bound split over two threads returns the one-lane result."""

from __future__ import annotations

import numpy as np
import pytest

from scanguard.geometry import inverse, transform_points
from scanguard.matching import _correlative as _k
from scanguard.matching import lanes
from scanguard.matching.config import CorrelativeConfig
from scanguard.matching.correlative import correlative_match, second_peak
from scanguard.matching.likelihood import LikelihoodGrid


@pytest.fixture
def two_lanes():
    lanes.set_search_lanes(2)
    yield
    lanes.set_search_lanes(1)


def _runs(grid, src, init, cfg):
    step = float(np.arccos(1 - grid.resolution**2 / (2 * 3.0**2)))
    n = int(np.ceil(cfg.window_theta / step))
    offsets = np.arange(-n, n + 1) * step
    w = int(np.ceil(cfg.window_xy / grid.resolution - 1e-9))
    return _k.discretise_runs(src, *init, offsets, *grid.origin, grid.resolution), w


def _case(seed, *, periodic=False):
    rng = np.random.default_rng(seed)
    if periodic:
        # a corridor of evenly spaced posts: equal scores at many offsets (ties)
        xs = np.arange(-4.0, 4.01, 0.4)
        mp = np.vstack([np.column_stack([xs, np.full_like(xs, y)]) for y in (-1.0, 1.0)])
        src = mp[np.abs(mp[:, 0]) < 2.5] - np.array([0.4, 0.0])
    else:
        mp = rng.uniform(-3, 3, size=(400, 2))
        true = rng.uniform(-0.1, 0.1, size=3)
        src = transform_points(inverse(true), mp[:150]) + rng.normal(0, 0.01, (150, 2))
        src = np.vstack([src, rng.uniform(-3, 3, size=(50, 2))])
    return mp, src


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("periodic", [False, True])
def test_two_lanes_give_the_one_lane_result(seed, periodic):
    mp, src = _case(seed, periodic=periodic)
    cfg = CorrelativeConfig(resolution=0.05, levels=4, window_xy=1.2, window_theta=0.2)
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = np.array([0.02 * seed, -0.03, 0.01 * seed])
    runs, w = _runs(grid, src, init, cfg)
    m = (2 * w) // 8 + 1
    assert runs[0].shape[0] * m * m >= lanes.MIN_LANE_CANDIDATES  # the split path is taken
    for threshold in (0.0, 0.2 * len(src)):
        for exclude in ((0, 0, -1.0), (3, -2, 16.0)):
            one = _k.branch_and_bound(grid.stack, grid.pad, *runs, w, 4, threshold, *exclude)
            lanes.set_search_lanes(2)
            try:
                two = lanes.branch_and_bound(grid.stack, grid.pad, runs, w, 4, threshold, exclude)
            finally:
                lanes.set_search_lanes(1)
            assert two[:4] == one[:4]  # the same pose and the same (exact) sum
            assert two[5] == one[5]  # (the count of scored candidates may differ)


def test_periodic_map_has_ties():
    """The periodic case really has several finest offsets of the best sum."""
    mp, src = _case(0, periodic=True)
    cfg = CorrelativeConfig(resolution=0.05, levels=4, window_xy=1.2, window_theta=0.2)
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = np.zeros(3)
    (ix, iy, wt, cnt), w = _runs(grid, src, init, cfg)
    best = _k.branch_and_bound(grid.stack, grid.pad, ix, iy, wt, cnt, w, 4, 0.0)[3]
    sums = _k.neighbourhood(grid.stack, grid.pad, ix, iy, wt, cnt, 0, 0, w)
    assert np.count_nonzero(sums == best) >= 2


def test_matches_and_second_peaks_unchanged_on_two_lanes(two_lanes):
    mp, src = _case(3, periodic=True)
    cfg = CorrelativeConfig(resolution=0.05, levels=4, window_xy=1.5, window_theta=0.3)
    grid = LikelihoodGrid.from_points(mp, cfg)
    init = np.array([0.1, 0.05, -0.02])
    two = correlative_match(src, grid, init, cfg)
    alias_two = second_peak(src, grid, init, two, cfg, radius=0.3, min_ratio=0.5)
    lanes.set_search_lanes(1)
    one = correlative_match(src, grid, init, cfg)
    alias_one = second_peak(src, grid, init, one, cfg, radius=0.3, min_ratio=0.5)
    np.testing.assert_array_equal(two.pose, one.pose)
    assert two.score == one.score
    np.testing.assert_array_equal(two.covariance, one.covariance)
    assert alias_two.found == alias_one.found
    np.testing.assert_array_equal(alias_two.pose, alias_one.pose)


def test_small_searches_stay_on_one_lane(two_lanes):
    rng = np.random.default_rng(1)
    mp = rng.uniform(-3, 3, size=(300, 2))
    cfg = CorrelativeConfig(resolution=0.05, levels=3, window_xy=0.1, window_theta=0.02)
    grid = LikelihoodGrid.from_points(mp, cfg)
    runs, w = _runs(grid, mp[:100], np.zeros(3), cfg)
    m = (2 * w) // 4 + 1
    assert runs[0].shape[0] * m * m < lanes.MIN_LANE_CANDIDATES
    got = lanes.branch_and_bound(grid.stack, grid.pad, runs, w, 3, 0.0)
    assert got == _k.branch_and_bound(grid.stack, grid.pad, *runs, w, 3, 0.0)  # n_eval too
    assert lanes.search_lanes() == 2
