"""What a run keeps per scan: compact records, the same results (issues 28 and 32)."""

from __future__ import annotations

import numpy as np
import pytest

from scanguard.errors import ConfigError
from scanguard.slam.config import RunConfig
from scanguard.slam.gmapping import _rows
from scanguard.slam.loop import LoopStep
from tests.test_loop import _loop, room, wheels  # noqa: F401 (fixtures)


def test_rows_keep_every_value_across_growth():
    rng = np.random.default_rng(3)
    want = rng.normal(size=(200, 3))
    rows = _rows.Rows(np.float64, (3,), capacity=4)
    for r in want:
        rows.append(r)
    assert len(rows) == 200
    np.testing.assert_array_equal(rows.values, want)
    np.testing.assert_array_equal(rows[-1], want[-1])
    assert rows.values.base is not None and rows._buf.shape[0] == 256  # doubled from 4
    with pytest.raises(IndexError):
        rows[200]


def test_rows_of_scalars_are_a_flat_array():
    flags = _rows.Rows(np.bool_)
    for k in range(70):
        flags.append(k % 3 == 0)
    assert flags.values.dtype == np.bool_
    assert flags.values.sum() == 24


def test_steps_keep_the_motion_numbers_of_decisions_but_not_its_arrays(room, wheels):  # noqa: F811
    cfg = RunConfig(backend="frontend", motion="fused")
    loop = _loop(room, cfg, wheels)
    seen: list[tuple[str, bool, float, bool]] = []

    def on_step(step: LoopStep, _a: int, _r: int) -> None:
        m = step.motion
        if m is not None:  # while seen, the step has the whole fused motion
            seen.append(
                (m.sources, m.wheels_flagged, m.mahalanobis2, bool(np.isfinite(m.covariance).all()))
            )

    loop.on_step = on_step
    res = loop.run(room.scans)
    kept = [s.motion for s in res.steps if s.motion is not None]
    assert len(kept) == len(room) - 1 == len(seen)
    assert all(finite for *_, finite in seen)
    for m, (sources, flagged, d2, _) in zip(kept, seen, strict=True):
        assert (m.sources, m.wheels_flagged) == (sources, flagged)
        assert m.mahalanobis2 == d2 or (np.isnan(m.mahalanobis2) and np.isnan(d2))
        assert np.isnan(m.increment).all() and np.isnan(m.covariance).all()
    assert not hasattr(res.steps[0], "__dict__")  # slotted: no per-step dict


def test_gmapping_keeps_compact_per_scan_records(room, wheels):  # noqa: F811
    cfg = RunConfig(backend="gmapping", motion="odometry")
    loop = _loop(room, cfg, wheels)
    loop.run(room.scans)
    be = loop.instances["cnn"].backend
    traj = be.trajectory()
    assert traj.shape == (len(room), 3) and np.isfinite(traj).all()
    assert be.used().dtype == np.bool_ and be.used().shape == (len(room),)
    assert be.used()[0]  # the first scan is always processed
    assert be.update_seconds.shape == (len(room),) and (be.update_seconds >= 0).all()
    assert len(be._scans) == int(be.used().sum())


def test_gmapping_gives_its_particle_maps_back_and_keeps_its_result(room, wheels):  # noqa: F811
    cfg = RunConfig(backend="gmapping", motion="odometry")
    loop = _loop(room, cfg, wheels)
    loop.run(room.scans)
    be = loop.instances["cnn"].backend
    traj, grid = be.trajectory(), be.grid()
    held = be.maps.nbytes
    be.release_particle_maps()
    assert be.maps.nbytes < held / 10
    np.testing.assert_array_equal(be.trajectory(), traj)
    again = be.grid()
    np.testing.assert_array_equal(again.logodds, grid.logodds)
    with pytest.raises(ConfigError, match="after release_particle_maps"):
        be.update(room.scans[0], wheels[0])
