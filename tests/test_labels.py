import math

import numpy as np
import pytest

from scanguard.errors import ConfigError
from scanguard.geometry import compose
from scanguard.pairs.labels import (
    AMBIGUOUS,
    FAULT,
    NORMAL,
    LabelConfig,
    assign_labels,
    mean_displacement,
    pair_errors,
)


def ring(radius: float, n: int = 360) -> np.ndarray:
    a = np.linspace(-np.pi, np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)


def test_pure_translation_moves_every_point_equally():
    pts = ring(4.0)
    assert mean_displacement([0.03, -0.04, 0.0], pts) == pytest.approx(0.05, abs=1e-12)


def test_rotation_lever_arm():
    # a rotation by a about the sensor moves a point at radius r by 2 r sin(a/2)
    a = math.radians(1.5)
    for r in (1.0, 5.0, 20.0):
        assert mean_displacement([0, 0, a], ring(r)) == pytest.approx(2 * r * math.sin(a / 2))


def test_pair_errors_of_injected_misalignment():
    reference = np.array([0.8, 0.1, 0.2])
    injected = np.array([0.12, 0.0, 0.0])
    estimate = compose(reference, injected)
    t, r, d = pair_errors(estimate, reference, ring(3.0))
    assert t == pytest.approx(0.12)
    assert r == pytest.approx(0.0, abs=1e-12)
    assert d == pytest.approx(0.12)


def test_labels_follow_thresholds():
    cfg = LabelConfig()
    pts = ring(5.0)
    ref = np.array([0.5, 0.0, 0.1])
    cases = {
        (0.02, 0.0, 0.0): NORMAL,  # 2 cm
        (0.085, 0.0, 0.0): AMBIGUOUS,  # between 7.5 and 10 cm
        (0.20, 0.0, 0.0): FAULT,  # 20 cm
        (0.0, 0.0, math.radians(0.3)): NORMAL,  # 2.6 cm at 5 m
        (0.0, 0.0, math.radians(1.5)): FAULT,  # 13 cm at 5 m (lever arm)
        (0.0, 0.0, math.radians(0.95)): AMBIGUOUS,  # 8.3 cm at 5 m
    }
    for err, want in cases.items():
        est = compose(ref, np.array(err))
        t, r, d = pair_errors(est, ref, pts)
        assert int(assign_labels(t, r, d, cfg)) == want, err


def test_translation_and_rotation_limits_apply_on_their_own():
    cfg = LabelConfig()
    # tiny displacement but a rotation above the fault limit -> fault
    assert assign_labels(0.0, math.radians(2.5), 0.01, cfg) == FAULT
    # translation above its fault limit -> fault even if the points barely move
    assert assign_labels(0.2, 0.0, 0.04, cfg) == FAULT
    # all three below the normal limits -> normal; one in the band -> ambiguous
    assert assign_labels(0.01, math.radians(0.2), 0.02, cfg) == NORMAL
    assert assign_labels(0.12, math.radians(0.2), 0.02, cfg) == AMBIGUOUS
    # non-finite errors (unknown answer) -> ambiguous, never fault (issue 11, item 8)
    assert assign_labels(np.nan, 0.0, np.nan, cfg) == AMBIGUOUS
    assert assign_labels(np.inf, 0.0, 0.01, cfg) == AMBIGUOUS


def test_vectorised_labels_shape_and_dtype():
    lab = assign_labels([0.0, 0.3], [0.0, 0.0], [0.01, 0.3])
    assert lab.dtype == np.int8
    assert lab.tolist() == [NORMAL, FAULT]


def test_threshold_order_validated():
    with pytest.raises(ConfigError, match="normal_displacement"):
        LabelConfig.from_dict({"normal_displacement": 0.2, "fault_displacement": 0.1})
