"""Hostile-input audit 2 (issue 24): library misuse and config domains (defects 13, 14, 15).

Each case has a known answer: a `ScanGuardError` subclass with a one-line message, a failed
match instead of a "converged" one, or a value capped with a warning.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import numpy as np
import pytest
from pydantic import ValidationError

from scanguard.dataset.config import EnvironmentSpec
from scanguard.detect.baselines.registry import load_detector
from scanguard.detect.detector import FaultDetector
from scanguard.errors import ConfigError, MatchingError, ModelError, ScanError
from scanguard.matching import get_matcher
from scanguard.matching.result import NO_INLIERS
from scanguard.runtime import executor as executor_mod
from scanguard.scan import LaserScan
from scanguard.slam.grid import GridConfig
from tests.helpers import make_sequence, room_segments

MATCHERS = ["icp", "icp-paper", "plicp", "correlative"]
PTS = np.random.default_rng(0).uniform(-5, 5, (200, 2))


# --- defect 13: library crashes -------------------------------------------------------------------


@pytest.mark.parametrize("name", MATCHERS)
@pytest.mark.parametrize("guess", [[1e20, 0, 0], [0, -1e12, 0], [1e300, 1e300, 0]])
def test_absurd_initial_guess_is_a_matching_error(name, guess):
    with pytest.raises(MatchingError, match=r"initial guess .* beyond \+-1e\+06 m"):
        get_matcher(name)(PTS, PTS, guess)


@pytest.mark.parametrize("name", MATCHERS)
def test_points_beyond_a_thousand_km_are_a_matching_error(name):
    with pytest.raises(MatchingError, match=r"source: points beyond \+-1e\+06 m"):
        get_matcher(name)(PTS + 1e20, PTS, None)


def test_initial_guess_of_1e20_does_not_kill_python():
    # the audit's SIGSEGV ran in the process itself: run it in a child to see its exit status
    code = (
        "import numpy as np\n"
        "from scanguard.matching import get_matcher\n"
        "from scanguard.errors import MatchingError\n"
        "pts = np.random.default_rng(0).uniform(-5, 5, (200, 2))\n"
        "try:\n"
        "    get_matcher('plicp')(pts, pts, [1e20, 0, 0])\n"
        "except MatchingError:\n"
        "    print('refused')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "refused", out.stderr[-400:]


@pytest.mark.parametrize("name", ["plicp", "correlative"])
def test_match_started_far_off_never_reports_converged(name):
    r = get_matcher(name)(PTS, PTS, [1e5, 0.0, 0.0])
    assert not r.converged and r.reason == NO_INLIERS and r.inlier_ratio == 0.0
    # and a good start still converges
    good = get_matcher(name)(PTS, PTS, [0.1, 0.0, 0.0])
    assert good.converged and np.abs(good.pose).max() < 1e-6


@pytest.fixture(scope="module")
def shipped() -> FaultDetector:
    return FaultDetector.load()


@pytest.fixture(scope="module")
def pair():
    seq = make_sequence(room_segments(), np.tile([0.06, 0.01, 0.02], (2, 1)))
    return seq[0], seq[1], get_matcher("icp-paper")(seq[1], seq[0])


@pytest.mark.parametrize(
    ("kw", "error", "message"),
    [
        ({"pose": "abc"}, MatchingError, "pose must be 3 numbers (x, y, theta), got str"),
        ({"pose": [0, 0]}, MatchingError, "pose must be 3 numbers (x, y, theta), got shape (2,)"),
        ({"pose": [0, 0, np.nan]}, MatchingError, "pose must be finite, got [0.0, 0.0, nan]"),
        (
            {"pose": [0, 0, 0], "odometry": np.zeros(2)},
            MatchingError,
            "odometry must be 3 numbers (x, y, theta), got shape (2,)",
        ),
        ({"pose": [0, 0, 0], "previous": "scan"}, ScanError, "previous must be a LaserScan"),
    ],
)
def test_fault_probability_misuse_raises_scanguard_errors(shipped, pair, kw, error, message):
    previous, current, match = pair
    args = {"previous": previous, "current": current, "match": match, **kw}
    with pytest.raises(error) as err:
        shipped.fault_probability(**args)
    assert message in str(err.value)
    p = shipped.fault_probability(previous, current, match.pose, match)
    assert 0.0 <= p <= 1.0


@pytest.mark.parametrize("ranges", ["abc", ["a", "b"], [[1.0], "x"]])
def test_string_ranges_are_a_scan_error(ranges):
    with pytest.raises(ScanError, match="scan ranges must be numbers"):
        LaserScan(stamp=0.0, ranges=ranges, angle_min=0.0, angle_increment=0.1, range_min=0.0,
                  range_max=1.0)  # fmt: skip


def test_unknown_matcher_model_is_refused_not_the_default():
    with pytest.raises(MatchingError, match=r"unknown matcher 'nope' \(known: correlative, icp"):
        FaultDetector.load(matcher="nope")
    assert str(FaultDetector.load(matcher="plicp").source).endswith("plicp.pt")


# --- defect 14: upper bounds ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [("sequences", 1_000_000_000), ("duration", 1e9), ("scan_stride", 10**9)],
)
def test_dataset_counts_have_upper_bounds(field, value):
    with pytest.raises(ValidationError, match=field):
        EnvironmentSpec(name="lobby", scenario="lobby", **{field: value})
    assert EnvironmentSpec(name="lobby", scenario="lobby", sequences=10_000).sequences == 10_000


def test_local_workers_are_capped_at_the_cpus(monkeypatch, caplog):
    monkeypatch.setattr(executor_mod, "available_cpus", lambda: 2)
    with caplog.at_level(logging.WARNING, logger="scanguard.runtime"):
        pool = executor_mod.make_executor("local", workers=6)
    assert pool.workers == 2
    assert "--workers 6 is more than the 2 CPU(s) of this machine; using 2" in caplog.text
    caplog.clear()
    assert executor_mod.make_executor("local", workers=2).workers == 2 and not caplog.text
    with pytest.raises(ConfigError, match="--workers must be >= 1"):
        executor_mod.make_executor("local", workers=0)


# --- defect 15: bad config values -----------------------------------------------------------------


@pytest.mark.parametrize(
    "values", [{"l_min": 5, "l_max": -5}, {"l_min": 0.0}, {"l_max": 0.0}, {"l_min": -1e9}]
)
def test_grid_log_odds_bounds_cannot_invert_the_map(values):
    with pytest.raises(ValidationError):
        GridConfig(**values)
    assert GridConfig(l_min=-2, l_max=3).l_max == 3


def test_rpe_delta_beyond_the_sequence_is_refused(shipped, tmp_path):
    from scanguard.apps.run import run_recording
    from scanguard.slam.config import RunConfig

    seq = make_sequence(room_segments(), np.tile([0.06, 0.01, 0.02], (4, 1)))
    out = tmp_path / "run"
    cfg = RunConfig(backend="frontend", rpe_delta=100_000, matcher="icp-paper")
    with pytest.raises(ConfigError) as err:
        run_recording(seq, shipped, out, config=cfg)
    assert "rpe_delta 100000 is not below the number of scans (5)" in str(err.value)
    assert not out.exists()  # refused before any work


@pytest.mark.parametrize("bad", ["Infinity", "-Infinity", "NaN"])
def test_baseline_threshold_of_infinity_is_refused_at_load(tmp_path, bad):
    from scanguard.detect.baselines.threshold import ThresholdDetector

    det = ThresholdDetector("mean_residual", "high", name="residual")
    det.fit({"mean_residual": np.array([0.1, 0.2, 0.9, 1.0])}, np.array([0, 0, 1, 1]))
    good = tmp_path / "good.json"
    good.write_text(json.dumps(det.to_dict()))
    assert load_detector(good).threshold == pytest.approx(det.threshold)  # type: ignore[attr-defined]
    path = tmp_path / "det.json"
    path.write_text(json.dumps(det.to_dict()).replace(f"{det.threshold!r}", bad, 1))
    assert bad in path.read_text()
    with pytest.raises(ModelError) as err:
        load_detector(path)
    text = str(err.value)
    assert text.startswith(f"{path}: not a valid detector file") and "must be finite" in text


@pytest.mark.parametrize("bad", [float("inf"), float("nan"), 7.0, -0.1])
def test_metrics_model_threshold_is_a_probability(bad):
    from scanguard.detect.baselines.metrics_model import MetricsModelDetector

    model = MetricsModelDetector()
    with pytest.raises(ConfigError, match="threshold must be a probability in"):
        model.threshold = bad
    model.threshold = 0.3
    assert model.threshold == 0.3


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("gmapping: {xmin: -1.0e9}", "xmin must lie within +-1e+05 m"),
        ("gmapping: {xmax: 1.0e9}", "xmax must lie within +-1e+05 m"),
        (
            "gmapping: {xmin: -1.0e4, xmax: 1.0e4, ymin: -1.0e4, ymax: 1.0e4}",
            "initial map of 1.6e+11 cells",
        ),
    ],
)
def test_gmapping_map_extent_is_bounded_and_one_line(tmp_path, text, problem):
    from scanguard.slam.config import RunConfig

    path = tmp_path / "run.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError) as err:
        RunConfig.from_yaml(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: gmapping") and problem in msg and "\n" not in msg
