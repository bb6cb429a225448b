"""Argument types shared by the command lines of every stage."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

__all__ = ["frame_rates", "image_size", "out_path", "parse_size", "positive_seconds"]


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
    rates: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or name.strip() in rates:
            raise argparse.ArgumentTypeError(f"{item!r}: give NAME=FPS once per video, e.g. cam0=59.94,cam1=30")
        rates[name.strip()] = _rate(value, item)
    return rates


def _rate(value: str, item: str) -> float:
    try:
        rate = float(value)
    except ValueError:
        rate = math.nan
    if not (math.isfinite(rate) and 0 < rate <= 100_000):
        raise argparse.ArgumentTypeError(f"{item!r}: a frame rate is a positive number of frames per second")
    return rate
