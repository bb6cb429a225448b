"""`dynrecon run VIDEO... --out WS [--labels labels.csv | --tracks tracks.csv] [--force]`."""

from __future__ import annotations

import argparse
from pathlib import Path

from dynrecon.errors import InputError
from dynrecon.pipeline import PipelineOptions, _default_register, run_stages
from sfm.register_cli import parse_scale
from tracking.options import TrackOptions


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "run", help="videos in, 3D motion out: register, track, solve, record, export",
        description="Run every stage whose inputs changed since the last run in WS (WS/pipeline.json keeps "
                    "their hashes): register -> track (labels) -> subject (static videos the background left out, "
                    "posed from the tracks) -> solve -> recording.rrd -> points3d.csv, points.trc, points.c3d.")
    parser.add_argument("videos", nargs="+", type=Path, metavar="VIDEO")
    parser.add_argument("--out", type=Path, required=True, metavar="WS", help="workspace folder")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--labels", type=Path, help="labels.csv to track (default: WS/labels.csv if present)")
    source.add_argument("--tracks", type=Path, help="ready 2D tracks (tracks.csv); no tracking")
    parser.add_argument("--skeleton", type=Path, help="skeleton JSON (points, connections) for the recording")
    parser.add_argument("--max-frames", type=int, default=_default_register().max_frames,
                        help="SfM frames per video at most (the others are localized)")
    parser.add_argument("--track-window", type=int, default=TrackOptions().win_size,
                        help="LK window side of the tracker, px (smaller for small markers)")
    parser.add_argument("--track-patch", type=int, default=TrackOptions().patch,
                        help="appearance patch side of the tracker, px (smaller for small markers)")
    parser.add_argument("--intrinsics", type=Path, default=None,
                        help="known intrinsics for registration (cameras.json, calib .toml or .qca); kept fixed")
    parser.add_argument("--scale", default=None, metavar="A,B,METRES",
                        help="distance between two tracked points: the scale of static videos posed from the subject")
    parser.add_argument("--units", default="mm", help="unit label of the TRC/C3D exports")
    parser.add_argument("--force", action="store_true", help="redo every stage")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    register = _default_register()
    register.max_frames = args.max_frames
    register.intrinsics = args.intrinsics
    register.scale = parse_scale(args.scale)
    if args.track_window < 5 or args.track_patch < 5 or args.max_frames < 2:
        raise InputError(None, "--track-window and --track-patch must be >= 5 px, --max-frames >= 2")
    track = TrackOptions(win_size=args.track_window, patch=args.track_patch)
    options = PipelineOptions(register=register, track=track, labels=args.labels, tracks=args.tracks,
                              skeleton=args.skeleton, units=args.units, force=args.force)
    result = run_stages(args.videos, args.out, options)
    for stage in result.stages:
        print(f"{stage.name:9s} {'skipped (up to date)' if stage.skipped else f'{stage.seconds:.1f} s'}")  # noqa: T201
    if (result.workspace / "recording.rrd").is_file():
        print(f"open the recording with: rerun {result.workspace / 'recording.rrd'}")  # noqa: T201
    return 0
