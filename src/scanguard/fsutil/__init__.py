"""The output layer: every file and folder scanguard writes goes through this module.

* `check_output_path` checks a destination before any long work: the kind (regular file or
  folder), never a device, FIFO or socket, an extension the command can write, and a parent
  it can write in. Symbolic links are followed: scanguard writes to their target and never
  replaces the link itself.
* `atomic_path` (and `atomic_write_text` / `atomic_write_bytes`) writes one file to a
  temporary sibling and renames it into place, so a crash or Ctrl-C never leaves a
  half-written file and an existing file is only replaced once the new one is complete.
* `ResultDir` writes a whole result folder the same way: into a temporary sibling folder,
  moved into place at the end with a completion marker (`MARKER`: the command line, the
  version, the time and the files written). It refuses to write into a folder that scanguard
  did not create unless ``overwrite`` is given, and then replaces only scanguard's own files.
* `BatchDir` claims a folder that a command fills piece by piece (``run-many``: one result
  folder per recording, then one table), with the same refusal of a user's folder.
* Temporaries carry the writer's process id in their name (``.<name>.sg<pid>-<random>...``);
  the ones left behind by a killed process are removed by the next write to the same place
  (`clean_stale_temporaries`).
"""

from scanguard.fsutil._paths import (
    OutputKind,
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    check_file_name,
    check_output_path,
    child_path,
    clean_stale_temporaries,
    disk_full_error,
    is_disk_full,
    load_figure_writer,
    resolve_output,
    save_figure,
    temporary_prefix,
)
from scanguard.fsutil._result import MARKER, BatchDir, ResultDir, is_complete_result, read_marker

__all__ = [
    "MARKER",
    "BatchDir",
    "OutputKind",
    "ResultDir",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_file_name",
    "check_output_path",
    "child_path",
    "clean_stale_temporaries",
    "disk_full_error",
    "is_complete_result",
    "is_disk_full",
    "load_figure_writer",
    "read_marker",
    "resolve_output",
    "save_figure",
    "temporary_prefix",
]
