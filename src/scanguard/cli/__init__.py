"""Command-line interface: one module per command group; they parse, call the library, print.

``scanguard.cli:app`` is the console script. Importing this package registers every command
on it: each module adds its commands to `scanguard.cli.main.app`, in the order of
`COMMAND_MODULES` (the order of ``scanguard --help``).
"""

import importlib

from scanguard.cli.main import app

#: The command modules, in the order their commands are listed by ``scanguard --help``.
COMMAND_MODULES = (
    "info",
    "simulate",
    "dataset",
    "train",
    "evaluate",
    "calibrate",
    "export",
    "run",
    "run_many",
    "node",
)

for _name in COMMAND_MODULES:
    importlib.import_module(f"{__name__}.{_name}")

__all__ = ["COMMAND_MODULES", "app"]
