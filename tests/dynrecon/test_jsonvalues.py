"""Reports are strict JSON: a number that is not finite is written as null."""

import json
import math

import numpy as np

from dynrecon.jsonvalues import finite_or_none, float_or_nan, json_safe


def test_json_safe_replaces_every_non_finite_float_at_any_depth() -> None:
    report = {"a": math.nan, "b": [1.5, math.inf, {"c": np.float64(-np.inf), "d": (2, np.nan)}], "e": "nan", "f": 3}
    safe = json_safe(report)
    assert safe == {"a": None, "b": [1.5, None, {"c": None, "d": [2, None]}], "e": "nan", "f": 3}
    json.dumps(safe, allow_nan=False)  # would raise on a NaN left behind


def test_a_null_reads_back_as_nan() -> None:
    assert finite_or_none(math.nan) is None and finite_or_none(1.23456, 2) == 1.23
    assert math.isnan(float_or_nan(None)) and float_or_nan("2.5") == 2.5
