"""Checks of numeric and choice arguments, each refused with a one-line error naming the
argument (a CLI option such as ``--seed``, or a function's parameter), so that a negative seed,
``nan`` or ``inf`` never reaches the code: it could crash there, or pass comparisons that NaN
always fails (a NaN tolerance that "repairs" any pose). The library's configs and entry points
check what they take, once; the CLI passes values on and its :func:`~ultron.cli.common.command`
names the option of an error about a parameter."""

from __future__ import annotations

import math
import numbers

from ultron.errors import argument_error

#: Seeds are integers in [0, MAX_SEED]: the 32-bit range that every generator used accepts
#: (torch's takes up to 2⁶⁴ − 1 but no larger; NumPy's takes no negative seed).
MAX_SEED = 2**32 - 1


def _number(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def _describe(
    integer: bool, low: float | None, high: float | None, low_open: bool, high_open: bool
) -> str:
    kind = "an integer" if integer else "a finite number"
    if low is not None and high is not None:
        left, right = "(" if low_open else "[", ")" if high_open else "]"
        return f"{kind} in {left}{_number(low)}, {_number(high)}{right}"
    if low is not None:
        return f"{kind} {'>' if low_open else '≥'} {_number(low)}"
    if high is not None:
        return f"{kind} {'<' if high_open else '≤'} {_number(high)}"
    return kind


def check_range(
    option: str,
    value: float | None,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
) -> None:
    """Refuse a numeric option's value with a one-line error naming ``option`` (the CLI exits
    2) unless it is finite and within ``low``/``high`` (inclusive, or exclusive with
    ``low_open``/``high_open``); ``None`` (option not given) passes."""
    if value is None:
        return
    ok = math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        integer = isinstance(value, int) and not isinstance(value, bool)
        expected = _describe(integer, low, high, low_open, high_open)
        raise argument_error(option, f"expected {expected}, got {value!r}")


def check_fraction(name: str, value: object) -> None:
    """A one-line error naming ``name`` unless ``value`` is a real number (not a bool) in
    (0, 1]: a share of frames or labels."""
    number = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not (number and 0.0 < float(value) <= 1.0):  # type: ignore[arg-type]
        raise argument_error(name, f"expected a value in (0, 1], got {value!r}")


#: The largest count any option takes (iterations, points, frames …): beyond it no run ends.
MAX_COUNT = 10**9


def check_finite(name: str, value: object, minimum: float, strict: bool) -> None:
    """A one-line error naming ``name`` unless ``value`` is a finite number (not a bool)
    ≥ ``minimum`` (> ``minimum`` when ``strict``)."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < minimum or (strict and value == minimum):  # type: ignore[operator]
        relation = ">" if strict else "≥"
        raise argument_error(
            name, f"expected a finite number {relation} {minimum:g}, got {value!r}"
        )


def check_integer(name: str, value: object, low: int = 0, high: int | None = None) -> None:
    """A one-line error naming ``name`` unless ``value`` is an integer (not a bool) ≥ ``low``
    (and ≤ ``high`` when given)."""
    integer = isinstance(value, int) and not isinstance(value, bool)
    if not integer or value < low or (high is not None and value > high):  # type: ignore[operator]
        expected = f"≥ {low}" if high is None else f"in [{low}, {high}]"
        raise argument_error(name, f"expected an integer {expected}, got {value!r}")


def check_seed(name: str, value: object) -> None:
    """A seed must be an integer in [0, :data:`MAX_SEED`]."""
    check_integer(name, value, 0, MAX_SEED)


def check_count(name: str, value: object, minimum: int = 1) -> None:
    """A count (iterations, points, frames, threads …) must be an integer in
    [``minimum``, :data:`MAX_COUNT`]."""
    check_integer(name, value, minimum, MAX_COUNT)


def sweep_names(values: str | list[str] | None, option: str = "--sweeps") -> list[str] | None:
    """Sweep names from ``option``: one comma-separated string or repeated values, each
    possibly comma-separated; None (unset): every sweep. An empty name is a one-line error."""
    if not values:
        return None
    given = [values] if isinstance(values, str) else list(values)
    names = [name.strip() for value in given for name in value.split(",")]
    if not all(names):
        raise argument_error(option, f"expected comma-separated sweep names, got {values!r}")
    return names
