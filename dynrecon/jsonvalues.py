"""Numbers for JSON reports: JSON has no NaN or infinity, so a value that is not finite is written as null."""

from __future__ import annotations

import math

__all__ = ["finite_or_none"]


def finite_or_none(value: float | None, digits: int | None = None) -> float | None:
    """`value` as a float (rounded to `digits` when given), or None when it is None, NaN or infinite."""
    if value is None or not math.isfinite(value):
        return None
    return float(value) if digits is None else round(float(value), digits)
