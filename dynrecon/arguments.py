"""Argument types shared by the command lines of every stage."""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator
from pathlib import Path

__all__ = ["frame_rates", "image_size", "named_values", "out_path", "parse_size", "positive_seconds"]


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


def parse_size(value: str) -> tuple[int, int]:
    """WIDTHxHEIGHT: positive integers (a ValueError otherwise)."""
    parts = value.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f"{value!r} is not WIDTHxHEIGHT (e.g. 1280x1024)") from None
    if width <= 0 or height <= 0:
        raise ValueError(f"{value!r}: width and height must be positive")
    return width, height


def image_size(text: str) -> tuple[int, int]:
    """--size WxH."""
    try:
        return parse_size(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def frame_rates(text: str) -> float | dict[str, float]:
    """--fps: one rate for every video (30), or one per video (cam0=59.94,cam1=30)."""
    if "=" not in text:
        return _rate(text, text)
    return {name: _rate(value, item) for name, value, item in named_values(text, "NAME=FPS", "cam0=59.94,cam1=30")}


def named_values(text: str, form: str, example: str) -> Iterator[tuple[str, str, str]]:
    """NAME=VALUE,... -> (name, value's text, the item) per item, in order; an argparse error for an item without a
    name or `=`, or a name given twice (`form`, `example`: e.g. NAME=SECONDS, cam2=0.033, for its message)."""
    seen: set[str] = set()
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or name.strip() in seen:
            raise argparse.ArgumentTypeError(f"{item!r}: give {form} once per video, e.g. {example}")
        seen.add(name.strip())
        yield name.strip(), value, item


def _rate(value: str, item: str) -> float:
    try:
        rate = float(value)
    except ValueError:
        rate = math.nan
    if not (math.isfinite(rate) and 0 < rate <= 100_000):
        raise argparse.ArgumentTypeError(f"{item!r}: a frame rate is a positive number of frames per second")
    return rate
