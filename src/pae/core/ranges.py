"""The range checks of the settings records' ``__post_init__``: each raises a one-line
ValueError naming the setting (the config checks name it with its key:
``data.batch_size must be an integer >= 1, got 0``). Imports neither numpy nor torch."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from typing import Any


def is_int(value: Any) -> bool:
    """An integer that is not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A finite int or float that is not a bool."""
    return is_int(value) or (isinstance(value, float) and math.isfinite(value))


def check_integer(name: str, value: Any, low: int, optional: bool = False) -> None:
    """An integer >= ``low`` (with ``optional``: or None)."""
    if not (optional and value is None) and (not is_int(value) or value < low):
        alternative = "null or " if optional else ""
        raise ValueError(f"{name} must be {alternative}an integer >= {low}, got {value!r}")


def check_number(
    name: str, value: Any, low: float, strict: bool = False, optional: bool = False
) -> None:
    """A number > ``low`` (``strict``) or >= ``low`` (with ``optional``: or None)."""
    if optional and value is None:
        return
    if not is_number(value) or (value <= low if strict else value < low):
        bound = f"> {low:g}" if strict else f">= {low:g}"
        raise ValueError(f"{name} must be a number {bound}, got {value!r}")


def check_boolean(name: str, value: Any) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be true or false, got {value!r}")


def check_choice(name: str, value: Any, choices: Iterable[Any]) -> None:
    choices = list(choices)
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}; choose one of {choices}")
