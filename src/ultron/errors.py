"""Error types. Every error a user can cause is an :class:`UltronError` with a one-line message
that names the file or argument and says what was expected; the CLI prints it and exits 2."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

_Config = TypeVar("_Config")


class UltronError(Exception):
    """Base class of errors a user can act on (bad input, missing files, no surface)."""


class UltronInputError(UltronError, ValueError):
    """Invalid input: a file, a field inside it, or a function argument.

    The message has the form ``"<where>: <field>: <problem>"`` where ``where`` is the file
    path (or ``argument``) and ``field`` names the offending entry.
    """

    def __init__(self, where: str | Path, field: str, problem: str) -> None:
        self.where = str(where)
        self.field = field
        self.problem = problem
        super().__init__(f"{self.where}: {field}: {problem}")


def argument_error(name: str, problem: str) -> UltronInputError:
    """An :class:`UltronInputError` about a function or CLI argument called ``name``."""
    return UltronInputError("argument", name, problem)


def config_from_dict(cls: type[_Config], data: Mapping[str, Any], name: str) -> _Config:
    """``cls(**data)`` for a config dataclass read from JSON; unknown or missing entries become
    an :func:`argument_error` naming ``name`` instead of a TypeError."""
    try:
        return cls(**data)
    except TypeError as exc:
        raise argument_error(name, f"unexpected entries ({exc})") from None
