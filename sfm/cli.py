"""Subcommands of the `sfm` stage."""

from __future__ import annotations

import argparse


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register this stage's subcommands on the main parser."""
