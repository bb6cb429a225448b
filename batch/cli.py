"""`dynrecon batch CAPTURE_DIR... --out DIR [--scheduler ADDRESS] [--workers N] [--calibration FILE]`: many
captures on Dask.

The parser's defaults come from the pipeline, which loads every stage, and Dask loads in the handler: `dynrecon`
builds this parser only when `batch` is chosen (see `COMMANDS`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from dynrecon.arguments import out_path

COMMANDS = {"batch": "many capture folders on Dask (this machine, or a cluster's scheduler): `run` for each"}


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    from dynrecon.pipeline import default_register
    from dynrecon.pipeline_cli import add_calibration_arguments, add_units_argument
    from tracking.options import TrackOptions

    parser = subparsers.add_parser(
        "batch",
        help=COMMANDS["batch"],
        description="Run the pipeline of `dynrecon run` on every capture folder (its videos, and optionally "
        "labels.csv or tracks.csv, a calibration, skeleton.json, capture.json: see docs/formats.md) into "
        "DIR/<capture>/. Per-video work (probing, tracking) runs as parallel tasks; registration and the solve "
        "are one task per capture. DIR/batch.json says, per capture, its status, stage, seconds and error. A "
        "rerun skips what is up to date.",
    )
    parser.add_argument("captures", nargs="+", type=Path, metavar="CAPTURE_DIR")
    parser.add_argument("--out", type=out_path, required=True, metavar="DIR", help="batch folder (one workspace each)")
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://host:8786); default: this machine"
    )
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes on this machine (default: one per core); with --scheduler: wait for N workers",
    )
    parser.add_argument("--retries", type=int, default=2, help="extra tries of a task that crashed (default 2)")
    parser.add_argument(
        "--max-frames", type=int, default=default_register().max_frames, help="SfM frames per video at most"
    )
    parser.add_argument(
        "--sfm-threads",
        type=int,
        default=default_register().num_threads,
        help="COLMAP threads of each registration (default -1: all cores of its machine)",
    )
    parser.add_argument("--track-window", type=int, default=TrackOptions().win_size, help="LK window side, px")
    parser.add_argument("--track-patch", type=int, default=TrackOptions().patch, help="appearance patch side, px")
    add_calibration_arguments(
        parser,
        "one lab calibration for every capture that has none of its own (what `dynrecon import-calibration` "
        "reads): imported instead of the SfM registration",
    )
    add_units_argument(parser)
    parser.add_argument("--force", action="store_true", help="redo every stage of every capture")
    parser.set_defaults(func=_batch)


def _batch(args: argparse.Namespace) -> int:
    from batch.graph import BatchOptions, run_batch
    from dynrecon.errors import InputError
    from dynrecon.pipeline import PipelineOptions, default_register
    from dynrecon.pipeline_cli import calibration_options, check_track_flags
    from tracking.options import TrackOptions

    check_track_flags(args)
    if (args.workers is not None and args.workers < 1) or args.retries < 0:
        raise InputError(None, "--workers must be >= 1 and --retries >= 0")
    if args.synchronized and args.offsets:  # else every capture fails alike
        raise InputError(
            None, "--synchronized and --offsets both given", fix="give one: --synchronized means every offset is 0"
        )
    if args.calibration is not None and not args.calibration.is_file():  # else every capture fails alike
        raise InputError(args.calibration, "is not a file: give the rig's calibration file with --calibration")
    if args.verbose < 2:  # the scheduler's and workers' start-up chatter, unless the user asks for debug output
        logging.getLogger("distributed").setLevel(logging.WARNING)
    pipeline = PipelineOptions(
        register=dataclasses.replace(
            default_register(),
            max_frames=args.max_frames,
            num_threads=args.sfm_threads,
            synchronized=args.synchronized,  # a capture without a calibration: its subject path
            offsets=args.offsets,  # the same names in every capture (a rig's fixed trigger delays)
            max_offset=args.max_offset,
        ),
        track=TrackOptions(win_size=args.track_window, patch=args.track_patch),
        calibration=args.calibration,
        calibration_options=calibration_options(args),
        units=args.units,
        force=args.force,
    )
    options = BatchOptions(
        pipeline=pipeline, scheduler=args.scheduler, workers=args.workers, retries=args.retries, progress=True
    )
    report = run_batch(args.captures, args.out, options)
    done = sum(1 for s in report.captures.values() if s.status == "done")
    print(f"{done} of {len(report.captures)} captures done; state in {report.out / 'batch.json'}")  # noqa: T201
    return 1 if report.failed else 0
