"""The detector checkpoint contract.

`train` writes checkpoints and `detector` reads them; the contract lives here so that neither
imports the other (no import circle detector -> train -> evaluate -> detector).
"""

#: The ``format`` field of a checkpoint written by `scanguard.detect.train.save_checkpoint`.
CHECKPOINT_FORMAT = "scanguard-fault-cnn"
#: The newest checkpoint layout this version reads and writes (2: adds the optional
#: ``calibration`` block of `scanguard.detect.calibrate`).
CHECKPOINT_VERSION = 2
#: The version a checkpoint with a ``calibration`` block is written with, so that an older
#: scanguard, which would silently ignore the block, refuses it instead.
CALIBRATED_VERSION = 2
