"""Numbers for JSON reports: JSON has no NaN or infinity, so a value that is not finite is written as null (and read
back as NaN)."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["finite_or_none", "float_or_nan", "json_safe"]


def finite_or_none(value: float | None, digits: int | None = None) -> float | None:
    """`value` as a float (rounded to `digits` when given), or None when it is None, NaN or infinite."""
    if value is None or not math.isfinite(value):
        return None
    return float(value) if digits is None else round(float(value), digits)


def float_or_nan(value: float | str | None) -> float:
    """A report's number read back: null (None) as NaN, anything else as `float()` reads it."""
    return math.nan if value is None else float(value)


def json_safe(value: Any) -> Any:
    """`value` with every float that is not finite, at any depth of its dicts, lists and tuples, as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    return value
