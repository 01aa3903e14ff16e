"""The online SLAM loop under the guard: judge, back ends, occupancy grids, metrics, `run`.

Modules, one per stage:

* `scanguard.slam.guard` - the judge (`ScanGuard`): match each scan to the previous one,
  render the pair, let the detector call it normal or faulty;
* `scanguard.slam.backend` - the `Backend` protocol and the `frontend` back end (scan-to-scan
  chaining of the guard's accepted matches, the baseline);
* `scanguard.slam.gmapping` - a Rao-Blackwellised particle filter after GMapping;
* `scanguard.slam.grid` - occupancy grids with map_server export;
* `scanguard.slam.metrics` - ATE/RPE (evo) and the Kümmerle relation metric;
* `scanguard.slam.run` - `scanguard run` / `demo` over a whole recording.

Import the modules themselves; this package imports nothing heavy on purpose.
"""
