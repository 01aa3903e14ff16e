"""The fault detector and everything around it, one module per step.

Modules, lowest first (each imports only modules listed before it, never one after it):

* `scanguard.detect.features` - derived metric columns and a pair store's feature table;
* `scanguard.detect.calibrate` - temperature/Platt scaling and the `Calibration` block;
* `scanguard.detect.render` - a matched pair as an image (numba kernels in
  `scanguard.detect._render_kernels`, the numpy reference in
  `scanguard.detect.render_reference`);
* `scanguard.detect.model` - the CNN presets and their inputs;
* `scanguard.detect.checkpoint` - the checkpoint format: writing, reading, validation;
* `scanguard.detect.baselines` - the classical detectors (`base`, `threshold`,
  `metrics_model`, `registry`);
* `scanguard.detect.images`, `scanguard.detect.torch_data` - rendering a pair store, the
  torch ``Dataset``;
* `scanguard.detect.detector` - the shipped `FaultDetector` (loading and inference);
* `scanguard.detect.evaluate` - Table-2-style evaluation, ROC, confusion matrices;
* `scanguard.detect.recalibrate` - calibrating a detector on a pair store, saving it;
* `scanguard.detect.train_config`, `scanguard.detect.distributed`,
  `scanguard.detect.train_epoch`, `scanguard.detect.train` - training;
* `scanguard.detect.protocol` - the held-out protocol of the model card.

Reference labels are `scanguard.pairs.labels`, scores and thresholds `scanguard.scoring`.
Import the modules themselves; this package imports nothing heavy on purpose.
"""
