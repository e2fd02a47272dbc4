"""The reconstruction methods by name, without importing them.

What the command line offers (``reconstruct --method`` and its help) and what the reports and
run records need to know about a method — whether it reads a fitted acoustic field — without
loading torch and every method's code. :mod:`ultron.methods.registry` attaches each name's
implementation and refuses, at import, a registry that lists other methods than this catalog.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MethodInfo:
    """A method's name (``reconstruct --method``) and whether it reads a fitted acoustic field
    (stage 1). What each method is: :mod:`ultron.methods.registry` and docs/reconstruct.md."""

    name: str
    needs_field: bool = False


CATALOG: tuple[MethodInfo, ...] = (
    MethodInfo("ultron", True),
    MethodInfo("ultron-noloss", True),
    MethodInfo("compounding"),
    MethodInfo("on"),
    MethodInfo("rocosdf"),
    MethodInfo("unsr-row"),
    MethodInfo("unsr-col"),
)
#: Every method's name, in the catalog's order.
METHOD_NAMES: tuple[str, ...] = tuple(info.name for info in CATALOG)
#: The methods that read a fitted acoustic field.
FIELD_METHODS: tuple[str, ...] = tuple(info.name for info in CATALOG if info.needs_field)
#: The ``method`` a ``finetune`` run records in its run.json: UltrON adapted to a new bone from
#: a trained network (it reads a fitted field; it is not a ``reconstruct --method``).
FINETUNE_METHOD = "ultron-finetune"
#: Every ``method`` a run.json may record whose run read a fitted acoustic field.
FIELD_RUN_METHODS: tuple[str, ...] = (*FIELD_METHODS, FINETUNE_METHOD)


def method_help() -> str:
    """The help line of ``--method``: ``"ultron, ultron-noloss, … or unsr-col."``."""
    return f"{', '.join(METHOD_NAMES[:-1])} or {METHOD_NAMES[-1]}."


__all__ = [
    "CATALOG",
    "FIELD_METHODS",
    "FIELD_RUN_METHODS",
    "FINETUNE_METHOD",
    "METHOD_NAMES",
    "MethodInfo",
    "method_help",
]
