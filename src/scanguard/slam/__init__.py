"""The online SLAM loop under the guard: judge, gate, back ends, occupancy grids, metrics, loop.

Modules, one per stage:

* `scanguard.slam.pair` - a scan with its points (`Frame`) and the matching of two scans;
* `scanguard.slam.judge` - the judge: ``Judge(previous, current, match, odometry) -> Verdict``
  (the CNN's fault probability and the classical score), and the `Detector` protocol;
* `scanguard.slam.gate` - the `Gate`: the one place a verdict becomes accept or reject;
* `scanguard.slam.guard` - `ScanPairs` (match + judge consecutive scans);
* `scanguard.slam.stream` - `ScanGuard` (pairs -> judge -> gate -> the ``frontend`` back end,
  for streaming use: one instance through the loop's per-scan step);
* `scanguard.slam.backend` - the `Backend` protocol and the `frontend` back end (scan-to-scan
  chaining of accepted matches with a motion prior, and its map);
* `scanguard.slam.registry` - back ends by name (``frontend``, ``gmapping``, ``graph``);
* `scanguard.slam.loop` - the per-scan loop of a run over several back-end instances
  (back end + gate each); `scanguard.slam.config` - its `RunConfig`;
* `scanguard.slam.oracle` - reference labels of matches (the ``oracle`` gate);
* `scanguard.slam.gmapping` - a Rao-Blackwellised particle filter after GMapping;
* `scanguard.slam.graph` - a pose graph with judged loop closures;
* `scanguard.slam.grid` - occupancy grids with map_server export;
* `scanguard.slam.metrics` - ATE/RPE (evo) and the Kümmerle relation metric.

``scanguard run`` / ``demo`` over a whole recording are apps (`scanguard.apps.run`,
`scanguard.apps.demo`). Import the modules themselves; this package imports nothing heavy on
purpose.
"""
