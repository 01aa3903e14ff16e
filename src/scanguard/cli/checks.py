"""Checks of option values before a command does any work (one-line errors)."""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import os
import shlex
import typing
from collections.abc import Callable
from typing import Any, TypeVar

import typer

from scanguard.errors import ConfigError

F = TypeVar("F", bound=Callable[..., Any])


@dataclasses.dataclass(frozen=True)
class Bound:
    """Accepted values of a numeric option: finite, and ``low <= v`` (``low < v`` if open)."""

    low: float | None = None
    open_low: bool = False
    high: float | None = None

    def problem(self, value: float) -> str | None:
        """Why ``value`` is not accepted (None: accepted)."""
        if isinstance(value, float) and math.isnan(value):
            return "is not a number (nan)"
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be a finite number, got {value}"
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return f"must be {'>' if self.open_low else '>='} {self.low:g}, got {value}"
        if self.high is not None and value > self.high:
            return f"must be <= {self.high:g}, got {value}"
        return None


NON_NEGATIVE = Bound(low=0)
POSITIVE = Bound(low=0, open_low=True)
AT_LEAST_ONE = Bound(low=1)


def _option_name(fn: Callable[..., Any], name: str) -> str:
    """The long flag of parameter ``name`` of ``fn`` (``Annotated`` or default declaration)."""
    hint = typing.get_type_hints(fn, include_extras=True).get(name)
    infos = [*getattr(hint, "__metadata__", ()), inspect.signature(fn).parameters[name].default]
    for info in infos:
        decls = getattr(info, "param_decls", None) or ()
        longs = [d for d in decls if isinstance(d, str) and d.startswith("--")]
        if longs:
            return str(longs[0].split("/")[0])
        if type(info).__name__ == "ArgumentInfo":
            return name.upper()
    return "--" + name.replace("_", "-")


def checked(**bounds: Bound) -> Callable[[F], F]:
    """Check numeric options against `Bound`s before the command runs (one-line errors).

    Example:
        >>> @app.command()  # doctest: +SKIP
        ... @guarded
        ... @checked(seed=NON_NEGATIVE, duration=POSITIVE)
        ... def simulate(seed: int = ..., duration: float = ...) -> None: ...
    """

    def deco(fn: F) -> F:
        sig = inspect.signature(fn)
        names = {name: _option_name(fn, name) for name in bounds}

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            given = sig.bind_partial(*args, **kwargs).arguments
            for name, bound in bounds.items():
                value = given.get(name)
                for v in value if isinstance(value, (list, tuple)) else [value]:
                    problem = None if v is None else bound.problem(v)
                    if problem is not None:
                        raise ConfigError(f"{names[name]} {problem}")
            return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return deco


def outputs(**checks: Callable[[str], object]) -> Callable[[F], F]:
    """Check output options (``name=check(value)``) before the command does any work.

    Example:
        >>> @outputs(preview=png_output)  # doctest: +SKIP
    """

    def deco(fn: F) -> F:
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            given = sig.bind_partial(*args, **kwargs).arguments
            for name, check in checks.items():
                if given.get(name) is not None:
                    check(str(given[name]))
            return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return deco


def bag_output(path: str) -> object:
    """A bag destination: one ``*.mcap`` file, or a bag folder (a name without extension)."""
    from scanguard.fsutil import check_output_path

    if path.lower().endswith(".mcap"):
        return check_output_path(path, "file", suffixes=(".mcap",))
    return check_output_path(path, "dir", suffixes=(".mcap", ""))


def png_output(path: str) -> object:
    """A ``*.png`` file destination."""
    from scanguard.fsutil import check_output_path

    return check_output_path(path, "file", suffixes=(".png",))


def command_record(ctx: typer.Context) -> dict[str, Any]:
    """The resolved command line of ``ctx`` (defaults included), for a result's marker."""
    params = dict(ctx.params)
    words = ["scanguard", *ctx.command_path.split()[1:]]
    for p in ctx.command.params:
        if p.name not in params:
            continue
        value = params[p.name]
        values = list(value) if isinstance(value, (list, tuple)) else [value]
        if p.param_type_name == "argument":
            words += [str(v) for v in values]
            continue
        flag = max((o for o in p.opts if o.startswith("--")), key=len, default=p.opts[0])
        if getattr(p, "is_flag", False):
            if value:
                words.append(flag)
            continue
        for v in values:
            if v is not None:
                words += [flag, str(v)]
    return {
        "name": ctx.command_path.split(maxsplit=1)[-1],
        "command": shlex.join(words),
        "options": params,
        "cwd": os.getcwd(),
    }


def result_dir(ctx: typer.Context, out: str, overwrite: bool) -> Any:
    """A `ResultDir` for ``--out``, checked now (before any long work)."""
    from scanguard.fsutil import ResultDir

    return ResultDir(out, overwrite=overwrite, record=command_record(ctx))
