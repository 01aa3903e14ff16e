"""Session 10's speed work on a real log: exact paths stay exact, the iSAM2 change stays close.

Reads the Freiburg benchmark log from the shared data folder (skipped when it is absent).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scanguard.io import read_sequence
from scanguard.io.relations import read_relations
from scanguard.slam.graph import GraphBackend, GraphConfig
from scanguard.slam.relations import relation_errors

BENCH = Path(__file__).resolve().parents[2] / "shared" / "data" / "benchmark"
LOG = BENCH / "intel.clf.gz"
#: Allowed change of the mean translational relation error from the partial relinearization
#: check (m); the whole logs moved by -0.0014 (Intel), +0.0001 (FR079), -0.0011 (ACES).
TOLERANCE = 0.003

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not LOG.is_file(), reason="shared benchmark data not present"),
]


def _run(seq, partial: bool) -> np.ndarray:  # type: ignore[no-untyped-def]
    # the fixed loop reach and the whole local map the tolerance was set with: with the
    # reach that follows the uncertainty (the default since session 19) the two differ by 6
    # mm on this excerpt, with the thinned local map (session 20) by 7 mm (0.0304 against
    # 0.0377): one closure more or less moves a 3000-scan excerpt that much
    cfg = GraphConfig(partial_relinearization=partial, loop_search_sigmas=0.0, local_map_thin=0.0)
    backend = GraphBackend(cfg, range_max=float(seq.sensor.range_max))
    for scan, odom in zip(seq.scans, np.asarray(seq.odometry), strict=True):
        backend.update(scan, odom)
    return backend.trajectory()


def test_partial_relinearization_keeps_the_relation_errors_within_tolerance() -> None:
    # 3000 scans: the first where the two differ (0.0390 against 0.0393 m when written;
    # the same at 1500)
    seq = read_sequence(LOG, max_scans=3000)
    relations = read_relations(BENCH / "intel.relations")
    stamps = np.array([s.stamp for s in seq.scans])
    full = relation_errors(stamps, _run(seq, False), relations)
    partial = relation_errors(stamps, _run(seq, True), relations)
    assert full.trans_mean < 0.1  # the run itself is sound (raw wheels, no guard)
    assert abs(partial.trans_mean - full.trans_mean) <= TOLERANCE
