"""Subcommands of the `labeling` stage. Imports only argparse at the top: the stage loads in the handler."""

from __future__ import annotations

import argparse
from pathlib import Path

COMMANDS = {"label": "label points by hand in a local web page (and track them)"}


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register this stage's subcommands on the main parser."""
    p = subparsers.add_parser(
        "label",
        help=COMMANDS["label"],
        description="Serve a local labeling page for the videos of a workspace. Labels are saved to "
        "WS/labels.csv on every click; the page's Track button writes WS/tracks.csv.",
    )
    p.add_argument("workspace", type=Path, metavar="WS", help="workspace folder (created if missing)")
    p.add_argument(
        "--videos",
        type=Path,
        nargs="+",
        metavar="V",
        help="video files (default: those remembered in WS/labeling.json, else WS/videos/*)",
    )
    names = p.add_mutually_exclusive_group()
    names.add_argument("--points", metavar="a,b,c", help="comma-separated point names")
    names.add_argument(
        "--skeleton", type=Path, metavar="FILE", help='JSON {"points": [...], "connections": [["a", "b"], ...]}'
    )
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=0, help="port (default: any free port)")
    p.add_argument("--cache-mb", type=int, default=256, help="memory bound of the frame cache in MiB (default 256)")
    p.set_defaults(func=_label)


def _announce(url: str) -> None:
    print(f"labeling page: {url}  (Ctrl+C to stop)", flush=True)  # noqa: T201 (the command's result)


def _label(args: argparse.Namespace) -> int:
    from dynrecon.errors import InputError
    from labeling.skeleton import Skeleton, parse_points, read_skeleton
    from labeling.stage import LabelOptions, run

    skeleton = Skeleton()
    if args.points:
        skeleton = parse_points(args.points)
    elif args.skeleton:
        skeleton = read_skeleton(args.skeleton)
    if not 0 <= args.port <= 65535:
        raise InputError(None, f"--port {args.port} is not a port number", fix="use 1..65535, or 0 for any")
    if args.cache_mb < 1:
        raise InputError(None, f"--cache-mb {args.cache_mb} must be at least 1")
    options = LabelOptions(
        videos=list(args.videos or []), skeleton=skeleton, host=args.host, port=args.port, cache_mb=args.cache_mb
    )
    run(args.workspace, options, on_ready=_announce)
    return 0
