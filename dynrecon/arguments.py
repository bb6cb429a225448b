"""Argument types shared by the command lines of every stage."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["out_path"]


def out_path(text: str) -> Path:
    """An output path; an empty one would silently mean the current folder."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must not be empty: name the output folder or file")
    return Path(text)
