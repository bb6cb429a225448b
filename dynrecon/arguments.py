"""Argument types shared by the command lines of every stage."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

__all__ = ["out_path", "positive_seconds"]


def out_path(text: str) -> Path:
    """An output path; an empty one would silently mean the current folder."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must not be empty: name the output folder or file")
    return Path(text)


def positive_seconds(text: str) -> float:
    """A positive, finite number of seconds."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a positive number of seconds")
    return value
