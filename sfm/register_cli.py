"""The `dynrecon register` subcommand (placeholder until the pipeline lands)."""

from __future__ import annotations

import argparse


def add_register_command(subparsers: argparse._SubParsersAction) -> None:
    """Register `dynrecon register` on the main parser."""
