"""The ``graph`` back end: pose-graph SLAM (gtsam iSAM2) with judged loop closures.

* `scanguard.slam.graph.config` - `GraphConfig` (Karto / slam_toolbox names where they exist);
* `scanguard.slam.graph.closure` - loop-closure candidates, reference labels, and the judges
  (``none``, ``classical``, ``cnn``, ``oracle``);
* `scanguard.slam.graph.backend` - `GraphBackend`, behind the `scanguard.slam.backend.Backend`
  protocol; how a closure enters it is `scanguard.slam.graph.intake`;
* `scanguard.slam.graph.features` - the run-time features of a closure candidate;
* `scanguard.slam.graph.judges` - the shipped judges (``learned`` and the fitted
  ``classical`` test) read from ``models/closure_judge.json``, and `judge_for_gate`.

Fitting those judges (and harvesting their training candidates) is an app:
`scanguard.apps.closure_judge` and `scanguard.apps.closure_harvest`.
"""

from scanguard.slam.graph.backend import GraphBackend
from scanguard.slam.graph.closure import (
    AcceptAll,
    AllOf,
    ClosureCandidate,
    ClosureJudge,
    ClosureJudgeConfig,
    ClosureLabelConfig,
    ClosureRecord,
    ClosureVerdict,
    DetectorClosureJudge,
    ReferenceClosureJudge,
    ResponseTest,
    closure_errors,
    closure_label,
)
from scanguard.slam.graph.config import GraphConfig
from scanguard.slam.graph.judges import judge_for_gate

__all__ = [
    "AcceptAll",
    "AllOf",
    "ClosureCandidate",
    "ClosureJudge",
    "ClosureJudgeConfig",
    "ClosureLabelConfig",
    "ClosureRecord",
    "ClosureVerdict",
    "DetectorClosureJudge",
    "GraphBackend",
    "GraphConfig",
    "ReferenceClosureJudge",
    "ResponseTest",
    "closure_errors",
    "closure_label",
    "judge_for_gate",
]
