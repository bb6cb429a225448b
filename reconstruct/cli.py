"""Subcommands of the reconstruction stage."""

from __future__ import annotations

import argparse


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register `solve` (and friends) on the main parser."""
