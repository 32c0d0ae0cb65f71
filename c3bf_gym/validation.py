"""One style of argument checking for every public entry point.

Each checker takes the *user's* parameter name and value and returns the value in its canonical
Python type, or raises ``ValueError`` whose message names the parameter, the value given and the
valid form. The rules:

* numbers are Python or numpy integers and floats; ``bool`` (and ``numpy.bool_``) and strings are
  rejected, never read as 0/1 or parsed;
* booleans must be ``bool`` or ``numpy.bool_``; ``"false"`` is not False;
* ranges are exactly two numbers ``(low, high)`` with ``low <= high``;
* choices are compared by equality and the error lists every valid choice;
* sequences are any iterable but a string, of items of one type, stored as a tuple.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np

__all__ = ["boolean", "choice", "integer", "number", "number_range", "sequence"]


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _bounds_text(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    parts = []
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        parts.append(f"{'<' if high_open else '<='} {high:g}")
    return " and ".join(parts)


def number(
    name: str,
    value: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    unit: str = "",
) -> float:
    """``value`` as a finite ``float`` within the bounds (``low_open``: ``> low``, else ``>= low``)."""
    bounds = _bounds_text(low, high, low_open, high_open)
    form = "a finite number" + (f" {bounds}" if bounds else "") + (f" [{unit}]" if unit else "")
    if not _is_number(value) or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    x = float(value)
    if low is not None and (x <= low if low_open else x < low):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    if high is not None and (x >= high if high_open else x > high):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    return x


def integer(name: str, value: Any, *, low: int | None = None) -> int:
    """``value`` as an ``int`` (Python or numpy integer, not bool) ``>= low``."""
    form = "an integer" + (f" >= {low}" if low is not None else "")
    if not isinstance(value, (int, np.integer)) or isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be {form}, got {value!r}")
    return int(value)


def boolean(name: str, value: Any) -> bool:
    """``value`` as a ``bool``; only ``True``/``False`` (or numpy's) are accepted."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def number_range(
    name: str, value: Any, *, low: float | None = None, low_open: bool = False, unit: str = ""
) -> tuple[float, float]:
    """``value`` as ``(low, high)`` floats, exactly two finite numbers with ``low <= high``, both
    within the lower bound."""
    bounds = _bounds_text(low, None, low_open, False)
    form = "(low, high): two finite numbers with low <= high" + (f", both {bounds}" if bounds else "")
    form += f" [{unit}]" if unit else ""
    if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    items = tuple(value)
    if len(items) != 2 or not all(_is_number(v) and math.isfinite(float(v)) for v in items):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    lo, hi = float(items[0]), float(items[1])
    if lo > hi or (low is not None and (lo <= low if low_open else lo < low)):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    return lo, hi


def choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """The entry of ``choices`` that ``value`` names: an equal string, or the very object (None)."""
    options = tuple(choices)
    for option in options:
        if value is option or (isinstance(value, str) and isinstance(option, str) and value == option):
            return option
    raise ValueError(f"unknown {name} {value!r}; valid choices: {', '.join(map(repr, options))}")


def sequence(name: str, value: Any, item_type: type | tuple[type, ...], form: str) -> tuple[Any, ...]:
    """``value`` as a tuple whose items are all ``item_type`` instances (a list or any iterable but
    a string); ``form`` describes it in the error, e.g. ``"a tuple of ObstacleSpec"``."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise ValueError(f"{name} must be {form}, got {value!r}")
    items = tuple(value)
    for item in items:
        if not isinstance(item, item_type):
            raise ValueError(f"{name} must be {form}, got {value!r} (an item is {item!r})")
    return items
