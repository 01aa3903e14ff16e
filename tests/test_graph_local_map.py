"""The graph's sequential match against its local map (`scanguard.slam.graph.local_map`)."""

from __future__ import annotations

import numpy as np
import pytest

import scanguard.slam.graph.local_map as lm
from scanguard.matching.likelihood import LikelihoodGrid
from scanguard.slam.graph import GraphConfig
from tests.helpers import room_segments
from tests.test_correlative import TRUE, local_map, scan_points


@pytest.fixture(scope="module")
def scene() -> tuple[LikelihoodGrid, np.ndarray, GraphConfig]:
    segs = room_segments()
    cfg = GraphConfig()
    return LikelihoodGrid.from_points(local_map(segs), cfg.sequential), scan_points(segs, TRUE), cfg


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Record how many starts each ICP call of `refine` gets."""
    calls: list[int] = []
    real = lm.match_starts

    def spy(metric, src, tgt, starts, cfg):  # type: ignore[no-untyped-def]
        calls.append(len(starts))
        return real(metric, src, tgt, starts, cfg)

    monkeypatch.setattr(lm, "match_starts", spy)
    return calls


def test_refine_from_the_prediction_runs_one_icp_and_keeps_its_pose(scene, monkeypatch):
    """A correlative pose equal to the prediction: the second start would repeat the first."""
    grid, src, cfg = scene
    start = TRUE + np.array([0.03, -0.02, 0.01])
    both = lm.refine(grid, src, start, start + np.array([1e-3, 0.0, 0.0]), 0.01, cfg)
    calls = _counting(monkeypatch)
    one = lm.refine(grid, src, start, start.copy(), 0.01, cfg)
    assert calls == [1]
    # the ICP converges to the room's pose from there, as it does with a second start nearby
    np.testing.assert_allclose(one, TRUE, atol=0.01)
    np.testing.assert_allclose(one, both, atol=1e-6)


def test_refine_from_two_poses_runs_both(scene, monkeypatch):
    grid, src, cfg = scene
    calls = _counting(monkeypatch)
    pose = TRUE + np.array([0.02, 0.0, 0.0])
    out = lm.refine(grid, src, pose, TRUE + np.array([0.0, 0.02, 0.0]), 0.01, cfg)
    assert calls == [2]
    np.testing.assert_allclose(out, TRUE, atol=0.01)


def test_a_thinned_local_map_matches_as_the_whole_one(scene):
    """A point per 2 cm square: 57 % of the points, the same pose to half a millimetre."""
    _, src, cfg = scene
    whole = local_map(room_segments())
    thin = lm.thin_points(whole, 0.02)
    assert len(thin) < 0.6 * len(whole)
    predicted = TRUE + np.array([0.08, -0.06, 0.03])
    a = lm.match_local(src, whole, predicted, cfg, {})
    b = lm.match_local(src, thin, predicted, cfg, {})
    assert a is not None and b is not None
    np.testing.assert_allclose(a[0], TRUE, atol=0.01)
    np.testing.assert_allclose(b[0], a[0], atol=5e-4)  # measured: 3e-5 m, 2e-6 rad
