"""Applications: the workflows behind the commands (run, demo, run-many, calibrate, ...)."""
