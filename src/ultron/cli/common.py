"""Shared CLI plumbing: one-line errors with exit code 2, and the consoles."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import typer
from rich.console import Console

from ultron.errors import UltronError

P = ParamSpec("P")
R = TypeVar("R")

#: Exit code for bad input, as for a usage error.
EXIT_BAD_INPUT = 2

console = Console()
err_console = Console(stderr=True, soft_wrap=True)


def user_errors(func: Callable[P, R]) -> Callable[P, R]:
    """Turn :class:`UltronError` into a one-line ``error: …`` message on stderr and exit 2."""

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return func(*args, **kwargs)
        except UltronError as exc:
            err_console.print(f"error: {exc}", markup=False, highlight=False)
            raise typer.Exit(EXIT_BAD_INPUT) from None

    return wrapper
