"""Classical scan-matching failure detectors, compared with the CNN in the same tables.

Every detector has the same small API (`scanguard.detect.baselines.base.FeatureDetector`):
``fit(features, labels, select=...)`` fits it on the training split and chooses its operating
threshold on the selection set ``select`` (the validation split: pairs it was not fitted on),
``predict_proba(features)`` returns a score in ``[0, 1]`` where higher means "more likely a
fault" (label 1), ``predict(features)`` returns 0/1, and ``threshold`` / ``name`` describe it.
``features`` is either a mapping of named columns (the keys of
`scanguard.matching.MatchResult.metrics` plus ``gmapping_score``) or a 2-D array.

The comparison with the CNN is meant to be fair, i.e. against what a careful user would
configure: every default detector reads only **scale-free** features (the same meaning for any
sensor and robot speed: `SCALE_FREE_METRICS_FEATURES`; raw counts, raw eigenvalues, the raw
GMapping score and the motion size are `SCALE_DEPENDENT_METRICS_FEATURES`), and every threshold
is chosen by the CNN's rule (`THRESHOLD_RULE`: maximum balanced accuracy on the selection set,
`scanguard.scoring.choose_threshold` for probabilities).

* `ThresholdDetector` — one quality metric and a direction (``"high"``: large values mean
  fault, e.g. the ICP residual; ``"low"``: small values mean fault, e.g. the inlier ratio, the
  smallest Hessian eigenvalue per inlier or the per-beam GMapping score). The threshold
  maximises the balanced accuracy (or the plain accuracy), so class imbalance does not push it
  to "everything is normal".
* `MetricsModelDetector` — gradient boosting (or logistic regression on standardised,
  log-compressed features) over the scale-free quality metrics together, its probability
  threshold chosen by `scanguard.scoring.choose_threshold`.
* ``gmapping_score`` (`scanguard.matching.quality.gmapping_score`) — GMapping's
  ``ScanMatcher::score`` with the previous scan as the map, read through its per-beam form.

`BASELINES` names the default set used in the evaluation table; `make_baseline` builds one,
`save_detector` / `load_detector` ship fitted ones (plain JSON: sklearn fits, but the fitted
model is stored as arrays and evaluated with numpy, `portable`; nothing is unpickled).

Modules (import them directly; this package re-exports nothing):

* `scanguard.detect.baselines.base` - feature names, the `FeatureDetector` protocol, the
  threshold rule and the column helpers every detector shares;
* `scanguard.detect.baselines.threshold` - `ThresholdDetector`;
* `scanguard.detect.baselines.metrics_model` - `MetricsModelDetector`;
* `scanguard.detect.baselines.registry` - `BASELINES`, `make_baseline`, save / load;
* `scanguard.detect.baselines.portable` - fitted models as plain arrays (no pickle, no sklearn);
* `scanguard.detect.baselines.convert` - one-off conversion of the former pickled files.
"""
