"""Numbers read from JSON files dali or others wrote (model.json, scale.json, manifests): a JSON
number may be a boolean, NaN, 1e999 or an integer of hundreds of digits that no float holds.
These helpers turn a value into a finite float or say it is not one, never raising."""

from __future__ import annotations

import math


def finite_number(value) -> float | None:
    """A JSON number as a finite float, else None (booleans, strings, NaN, inf, 10**400)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def finite_numbers(value, count: int, positive: bool = False) -> tuple[float, ...] | None:
    """A JSON list of `count` finite numbers (each > 0 when `positive`) as floats, else None."""
    if not isinstance(value, list | tuple) or len(value) != count:
        return None
    numbers = tuple(finite_number(v) for v in value)
    if any(n is None or (positive and n <= 0) for n in numbers):
        return None
    return numbers
