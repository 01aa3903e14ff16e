"""Configuration base: pydantic models that load from and save to YAML.

Every job saves the final (resolved) config next to its outputs with `save_config`, so a
result can always be traced back to the exact settings that produced it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from scanguard.errors import ConfigError
from scanguard.fsutil import atomic_write_text
from scanguard.safeload import load_yaml

T = TypeVar("T", bound="YamlModel")


class YamlModel(BaseModel):
    """A strict pydantic model (unknown keys are errors) with YAML round trips.

    No float of a config may be infinite or NaN (``allow_inf_nan=False``, inherited by every
    config model): YAML spells them ``.inf`` and ``.nan``, and one such value (a grid
    resolution, a motion noise) otherwise runs to a non-finite trajectory or a traceback
    deep in numpy instead of a one-line error naming the key.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @classmethod
    def from_yaml(cls: type[T], path: str | Path) -> T:
        """Load and validate a YAML file.

        Raises:
            ConfigError: The file is missing, not a regular file, not text, not YAML (or
                nested too deep, or an alias bomb), or does not validate; the message names
                the file and the offending key.
        """
        p = Path(path)
        # bounded: a FIFO, a binary file, an alias bomb or deep nesting is a one-line error
        data = load_yaml(p, what="config file", error=ConfigError)
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(
                f"{p}: not a config file (a YAML {type(data).__name__}, not a mapping)"
            )
        return cls.from_dict(data, source=str(p))

    @classmethod
    def from_dict(cls: type[T], data: dict[str, Any], source: str = "<dict>") -> T:
        """Validate a plain dict, with errors naming ``source`` and the bad key."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            first = exc.errors()[0]
            loc = ".".join(str(x) for x in first["loc"]) or "<root>"
            raise ConfigError(f"{source}: {loc}: {_problem(first)}") from None

    def to_yaml(self) -> str:
        """Serialise to YAML (JSON-compatible values only)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)

    def save(self, path: str | Path) -> Path:
        """Write the YAML atomically to ``path``."""
        p = Path(path)
        atomic_write_text(p, self.to_yaml())
        return p


def _problem(error: Any) -> str:
    """The message of one pydantic error; a NaN is said to be one, not out of some bound."""
    value = error.get("input")
    if isinstance(value, float) and math.isnan(value):
        return "is not a number (nan)"
    if isinstance(value, float) and math.isinf(value):
        return f"must be a finite number, got {value}"
    return str(error["msg"])


def save_config(config: BaseModel, out_dir: str | Path, name: str = "config.yaml") -> Path:
    """Save the resolved config of a job next to its outputs (``out_dir/name``)."""
    out = Path(out_dir) / name
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    return out
