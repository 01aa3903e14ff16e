"""The fault detector and everything around it, one module per step.

* `scanguard.detect.render` - a matched pair as an image;
* `scanguard.pairs.labels` - reference-based labels with documented thresholds;
* `scanguard.detect.model` - the CNN presets;
* `scanguard.detect.checkpoint` - the checkpoint format shared by train and detector;
* `scanguard.detect.train` - training;
* `scanguard.detect.calibrate` - temperature/Platt scaling, threshold rule, ECE, reliability;
* `scanguard.detect.evaluate` - Table-2-style evaluation, ROC, confusion matrices;
* `scanguard.detect.detector` - the shipped `FaultDetector`;
* `scanguard.detect.baselines` - the classical detectors.

Import the modules themselves; this package imports nothing heavy on purpose.
"""
