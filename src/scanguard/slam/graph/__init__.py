"""The ``graph`` back end: pose-graph SLAM (gtsam iSAM2) with judged loop closures.

* `scanguard.slam.graph.config` - `GraphConfig` (Karto / slam_toolbox names where they exist);
* `scanguard.slam.graph.closure` - loop-closure candidates, reference labels, and the judges
  (``none``, ``classical``, ``cnn``, ``oracle``);
* `scanguard.slam.graph.backend` - `GraphBackend`, behind the `scanguard.slam.backend.Backend`
  protocol;
* `scanguard.slam.graph.harvest` - labelled closure candidates from simulation (features,
  resumable cache);
* `scanguard.slam.graph.learn` - the learned closure judge (``learned``) and the classical
  test fitted on the same candidates, saved together in ``models/closure_judge.json``.
"""

from scanguard.slam.graph.backend import GraphBackend
from scanguard.slam.graph.closure import (
    AcceptAll,
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
    judge_for_gate,
)
from scanguard.slam.graph.config import GraphConfig

__all__ = [
    "AcceptAll",
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
