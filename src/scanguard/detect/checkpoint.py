"""The detector checkpoint contract.

`train` writes checkpoints and `detector` reads them; the contract lives here so that neither
imports the other (no import circle detector -> train -> evaluate -> detector).
"""

#: The ``format`` field of a checkpoint written by `scanguard.detect.train.save_checkpoint`.
CHECKPOINT_FORMAT = "scanguard-fault-cnn"
#: The newest checkpoint layout this version reads and writes.
CHECKPOINT_VERSION = 1
