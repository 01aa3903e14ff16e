"""Help text that reads like a Unix tool's: ``--out PATH``, ``--seed INT``, ``RECORDING``.

Typer labels a value by its Python type (``<str>``, ``<int>``) and an argument by its
parameter name in braces (``{recording}``). `UnixTyper` makes every command a `UnixCommand`,
which gives each value an upper-case metavar: the one an option declares (``PATH``, ``NAME``,
see `scanguard.cli.options`), else one from its type (``TEXT``, ``INT``, ``FLOAT``).
"""

from __future__ import annotations

from typing import Any

import typer
from typer.core import TyperArgument, TyperCommand

#: Metavar of a value whose option declares none, by typer's name of its type.
TYPE_METAVARS = {"str": "TEXT", "int": "INT", "float": "FLOAT", "Path": "PATH"}


class UnixArgument(TyperArgument):
    """A positional argument shown as ``NAME`` (usage and help), not ``{name} <str>``."""

    def display_type_rich(self, ctx: Any) -> str | None:
        """No type label after the argument's name: the metavar already says what it is."""
        return None

    def get_usage_pieces(self, ctx: Any) -> list[str]:
        """``NAME``, ``[NAME]`` when optional, ``NAME...`` when repeated."""
        name = self.metavar or str(self.name).upper()
        name = name if self.required else f"[{name}]"
        return [f"{name}..." if self.nargs != 1 else name]


def _metavar(param: Any) -> str:
    if isinstance(param, TyperArgument):
        return str(param.name).upper()
    element = param.bare_type().removeprefix("list[").removesuffix("]")
    return TYPE_METAVARS.get(element, "TEXT")


class UnixCommand(TyperCommand):
    """A command whose values all have an upper-case metavar (see the module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for param in self.params:
            if getattr(param, "is_flag", False):
                continue
            if param.metavar is None:
                param.metavar = _metavar(param)
            if type(param) is TyperArgument:
                # typer builds its own argument class and takes no other; only the display
                # differs, the subclass adds no state
                param.__class__ = UnixArgument


class UnixTyper(typer.Typer):
    """A `typer.Typer` whose commands are `UnixCommand`s."""

    def command(self, *args: Any, **kwargs: Any) -> Any:
        """`typer.Typer.command` with ``cls=UnixCommand`` unless another class is given."""
        kwargs.setdefault("cls", UnixCommand)
        return super().command(*args, **kwargs)
