"""Domain randomisation of simulated builds (`EnvironmentSpec.randomize`).

Every test is seeded and small: a few seconds of simulation, few beams, few pairs.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from scanguard.dataset import DatasetConfig, build_dataset, plan_build
from scanguard.dataset.config import DomainRandomization, EnvironmentSpec
from scanguard.dataset.randomize import draw_domain, thin_indices
from scanguard.dataset.tasks import _simulate
from scanguard.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]

#: ``DatasetConfig.from_yaml("configs/paper.yaml").fingerprint()`` before ``randomize``
#: existed: a config without it must keep resuming its old builds.
PAPER_FINGERPRINT = "9477fb03d4f5fa99"

#: A small randomisation for builds that also match (few beams, slow rates, few pairs).
SMALL = {
    "n_beams": [180, 240],
    "fov_deg": [180.0, 360.0],
    "range_max": [4.0, 80.0],
    "rate_hz": [2.0, 4.0],
    "thinned_fraction": 0.0,
    "max_pairs": 12,
}


def small_config(randomize: dict[str, Any], *, sequences: int = 2, duration: float = 3.0):
    return DatasetConfig.from_dict(
        {
            "name": "dr-tiny",
            "matcher": "icp-paper",
            "gmapping_score": False,
            "splits": {"val_sequences": 0, "test_sequences": 0, "seed": 0},
            "environments": [
                {
                    "name": "lobby_dr",
                    "scenario": "lobby",
                    "sequences": sequences,
                    "duration": duration,
                    "seed": 41,
                    "randomize": randomize,
                }
            ],
        }
    )


def test_same_seed_same_draw_and_arrays():
    spec = DomainRandomization(**SMALL)
    assert draw_domain(spec, 41, 3) == draw_domain(spec, 41, 3)
    item = plan_build(small_config(SMALL, sequences=1))[0]
    a, b = _simulate(item), _simulate(item)
    assert a.metadata["domain"] == b.metadata["domain"]
    assert len(a) == len(b) >= 2
    np.testing.assert_array_equal(a.reference, b.reference)
    for x, y in zip(a.scans, b.scans, strict=True):
        np.testing.assert_array_equal(x.ranges, y.ranges)


def test_sequences_and_seeds_differ():
    spec = DomainRandomization()
    draws = [draw_domain(spec, 1100, k) for k in range(12)]
    assert len({(d.n_beams, d.fov_deg, d.range_max, d.rate_hz) for d in draws}) == 12
    assert draw_domain(spec, 1100, 0) != draw_domain(spec, 2100, 0)
    assert draw_domain(spec, 1100, 0) != draw_domain(spec.model_copy(update={"seed": 1}), 1100, 0)


def test_every_draw_lies_in_its_range():
    spec = DomainRandomization()
    draws = [draw_domain(spec, s, k) for s in (0, 7, -3) for k in range(100)]

    def inside(value: float, pair: tuple[float, float]) -> bool:
        return pair[0] <= value <= pair[1]

    for d in draws:
        assert inside(d.n_beams, spec.n_beams) and isinstance(d.n_beams, int)
        assert inside(d.fov_deg, spec.fov_deg)
        assert inside(d.range_max, spec.range_max)
        assert inside(d.noise_std, spec.noise_std)
        assert inside(d.noise_rel, spec.noise_rel)
        assert inside(d.dropout_prob, spec.dropout_prob)
        if d.thinned:
            assert d.thin_distance is not None and d.thin_angle_deg is not None
            assert inside(d.rate_hz, spec.thin_rate_hz)
            assert inside(d.thin_distance, spec.thin_distance)
            assert inside(d.thin_angle_deg, spec.thin_angle_deg)
        else:
            assert d.thin_distance is None and d.thin_angle_deg is None
            assert inside(d.rate_hz, spec.rate_hz)
    thinned = np.mean([d.thinned for d in draws])
    assert 0.15 < thinned < 0.35  # thinned_fraction 0.25 of 300 draws
    # the ranges are covered, not just hit at one spot
    assert max(d.n_beams for d in draws) > 1200 and min(d.n_beams for d in draws) < 400
    rates = [d.rate_hz for d in draws if not d.thinned]
    assert min(rates) < 2.0 and max(rates) > 25.0
    # a fixed value (low == high) is that value
    fixed = DomainRandomization(n_beams=(360, 360), fov_deg=(270.0, 270.0), thinned_fraction=0)
    d = draw_domain(fixed, 5, 5)
    assert d.n_beams == 360 and d.fov_deg == 270.0 and not d.thinned


def test_built_files_have_the_drawn_sensor(tmp_path):
    cfg = small_config(SMALL)
    summary = build_dataset(cfg, tmp_path / "b", progress=False)
    assert len(summary.built) == 2
    spec = cfg.environments[0].randomize
    assert spec is not None
    for k in range(2):
        draw = draw_domain(spec, 41, k)
        with h5py.File(tmp_path / "b" / "sequences" / f"lobby_dr_{k:02d}.h5", "r") as f:
            meta = json.loads(str(f.attrs["meta_json"]))
            n = f["scans/n_beams"][()]
            inc = f["scans/angle_increment"][()]
            amin = f["scans/angle_min"][()]
            rmax = f["scans/range_max"][()]
            ranges = f["scans/ranges"][()]
            n_pairs = f["pairs/label"].shape[0]
        dom = meta["domain"]
        for key, val in draw.as_dict().items():
            assert dom[key] == pytest.approx(val) if isinstance(val, float) else dom[key] == val
        assert dom["pairs"] == n_pairs <= spec.max_pairs
        assert np.all(n == draw.n_beams)
        full = draw.fov_deg >= 360.0 - 1e-9
        span = inc * (n if full else n - 1)
        np.testing.assert_allclose(np.degrees(span), draw.fov_deg, rtol=1e-5)
        np.testing.assert_allclose(np.degrees(-2 * amin) if not full else 360.0, draw.fov_deg)
        np.testing.assert_allclose(rmax, draw.range_max, rtol=1e-6)
        finite = ranges[np.isfinite(ranges)]
        assert finite.size and finite.max() <= draw.range_max + 1e-3
    # the draws differ between the two sequences, and so do the files
    assert draw_domain(spec, 41, 0).n_beams != draw_domain(spec, 41, 1).n_beams


def test_fast_rates_are_bounded_by_max_pairs():
    cfg = small_config({**SMALL, "rate_hz": [40.0, 40.0], "max_pairs": 5}, sequences=1)
    item = plan_build(cfg)[0]
    seq = _simulate(item)
    dom = seq.metadata["domain"]
    assert len(seq) - 1 == dom["pairs"] <= 5
    assert dom["simulated_duration"] == pytest.approx(5 / 40.0)


def test_thinned_steps_are_about_d():
    spec = {
        **SMALL,
        "thinned_fraction": 1.0,
        "thin_rate_hz": [20.0, 20.0],
        "thin_distance": [0.5, 0.6],
        "thin_angle_deg": [30.0, 30.0],
        "max_pairs": 50,
    }
    cfg = small_config(spec, sequences=1, duration=6.0)
    item = plan_build(cfg)[0]
    seq = _simulate(item)
    dom = seq.metadata["domain"]
    assert dom["thinned"] and dom["simulated_scans"] > dom["scans"] >= 3
    d, a = dom["thin_distance"], math.radians(dom["thin_angle_deg"])
    ref = np.asarray(seq.reference)
    step = np.hypot(*np.diff(ref[:, :2], axis=0).T)
    turn = np.abs((np.diff(ref[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
    # every step reached d (or the angle), and overshoots by at most one scanner period of
    # motion (the robot's top speed is 1.2 m/s: 0.06 m at 20 Hz)
    assert np.all((step >= d - 1e-9) | (turn >= a - 1e-9))
    moved = step[turn < a]
    assert moved.size and np.all(moved <= d + 1.2 / 20.0 + 1e-6)


def test_thin_indices_on_known_poses():
    x = np.arange(0.0, 5.01, 0.1)
    poses = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    idx = thin_indices(poses, 1.0, math.radians(30))
    np.testing.assert_allclose(poses[idx, 0], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0], atol=0.11)
    # turning on the spot: kept by the angle
    th = np.radians(np.arange(0, 100, 10.0))
    spin = np.stack([np.zeros_like(th), np.zeros_like(th), th], axis=1)
    assert thin_indices(spin, 1.0, math.radians(25)).tolist() == [0, 3, 6, 9]
    assert thin_indices(np.zeros((0, 3)), 1.0, 1.0).size == 0


def test_config_without_randomize_keeps_its_fingerprint():
    paper = DatasetConfig.from_yaml(ROOT / "configs" / "paper.yaml")
    assert paper.fingerprint() == PAPER_FINGERPRINT
    assert all("randomize" not in e for e in paper.model_dump(mode="json")["environments"])
    data = paper.model_dump(mode="json")
    for env in data["environments"]:
        env["randomize"] = None  # written out explicitly: the same config
    assert DatasetConfig.from_dict(data).fingerprint() == PAPER_FINGERPRINT
    # with it, the fingerprint changes (a resume refuses the old files)
    data["environments"][0]["randomize"] = {}
    assert DatasetConfig.from_dict(data).fingerprint() != PAPER_FINGERPRINT


def test_transfer_config_loads():
    cfg = DatasetConfig.from_yaml(ROOT / "configs" / "transfer.yaml")
    names = {e.name: e for e in cfg.environments}
    paper = DatasetConfig.from_yaml(ROOT / "configs" / "paper.yaml")
    for env in paper.environments:
        assert names[env.name] == env  # the paper's environments, unchanged
    dr = [e for e in cfg.environments if e.randomize is not None]
    assert sorted(e.name for e in dr) == ["corridor_dr", "glass_dr", "hall_dr", "lobby_dr"]
    assert all(e.sequences == 12 and not e.heldout for e in dr)
    assert names["office"].heldout and names["office"].randomize is None
    paper_seeds = {e.seed + k for e in paper.environments for k in range(e.sequences)}
    assert not paper_seeds & {e.seed + k for e in dr for k in range(e.sequences)}


@pytest.mark.parametrize(
    ("bad", "field"),
    [
        ({"fov_deg": [300.0, 200.0]}, "fov_deg"),
        ({"n_beams": [1, 100]}, "n_beams"),
        ({"range_max": [0.0, 10.0]}, "range_max"),
        ({"rate_hz": [1.0, 400.0]}, "rate_hz"),
        ({"thin_distance": [1.2, 0.5]}, "thin_distance"),
        ({"thinned_fraction": 1.5}, "thinned_fraction"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_bad_ranges_are_config_errors_naming_the_field(bad, field):
    with pytest.raises(ConfigError, match=field):
        small_config(bad)
    with pytest.raises(ConfigError, match=field):
        EnvironmentSpec.from_dict({"name": "x", "scenario": "lobby", "randomize": bad})


def test_other_overrides_still_apply_and_plain_builds_have_no_domain():
    cfg = small_config(SMALL, sequences=1)
    data = cfg.model_dump(mode="json")
    env = data["environments"][0]
    env["overrides"] = {"people": {"count": 3}, "sensor": {"n_beams": 90}, "stride": 3}
    seq = _simulate(plan_build(DatasetConfig.from_dict(data))[0])
    draw = draw_domain(DomainRandomization(**SMALL), 41, 0)
    assert seq.metadata["n_people"] == 3  # kept
    assert seq.scans[0].n_beams == draw.n_beams  # the draw wins over the same key
    assert seq.metadata["stride"] == 1 and seq.metadata["scan_rate_hz"] == draw.rate_hz
    # without randomize: nothing drawn, nothing recorded
    del env["randomize"]
    env["duration"] = 1.0
    plain = _simulate(plan_build(DatasetConfig.from_dict(data))[0])
    assert "domain" not in plain.metadata and plain.scans[0].n_beams == 90
