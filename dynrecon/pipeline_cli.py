"""`dynrecon run VIDEO... --out WS [--labels labels.csv | --tracks tracks.csv] [--calibration FILE] [--force]` and
`dynrecon demo`.

Both parsers take their defaults from the pipeline, which loads every stage: `dynrecon` builds them only when one of
`COMMANDS` is chosen.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

from dynrecon.arguments import out_path, positive_seconds

if TYPE_CHECKING:
    from dynrecon.pipeline import PipelineOptions
    from sfm.options import ImportCalibrationOptions

log = logging.getLogger(__name__)

COMMANDS = {
    "demo": "run the whole job on the embedded video sample and score it",
    "run": "videos in, 3D motion out: register, track, solve, record, export",
    "export": "a solve's points3d.csv as TRC and C3D files (what run exports), e.g. after a solve without videos",
}


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    _add_demo(subparsers)
    _add_run(subparsers)
    _add_export(subparsers)


def _add_export(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export",
        help=COMMANDS["export"],
        description="Write SOLVED/points.trc and SOLVED/points.c3d from the points3d.csv and sequencing.json that "
        "`dynrecon solve --out SOLVED` wrote, ordered and timed as `dynrecon run` exports them.",
    )
    # `out`, as every writing command names its folder: dynrecon/cli.py locks it
    parser.add_argument("out", type=Path, metavar="SOLVED", help="the folder `dynrecon solve` wrote")
    parser.add_argument("--cameras", type=Path, required=True, help="the cameras.json the solve used")
    parser.add_argument(
        "--units",
        required=True,
        help="the cameras' world unit, written as the exports' unit: m after import-calibration (times its "
        "--scale) or register with --scale / --board; an SfM world without them has an arbitrary scale",
    )
    parser.set_defaults(func=_export_command)


def _export_command(args: argparse.Namespace) -> int:
    from dynrecon.errors import InputError
    from dynrecon.pipeline import export_points, registered_in_metres
    from reconstruct.outputs.export import check_units

    check_units(args.units)  # before anything is read
    for path in (args.out / "points3d.csv", args.out / "sequencing.json", args.cameras):
        if not path.is_file():
            raise InputError(
                path, "file not found", fix="give the folder `dynrecon solve --out` wrote, and its cameras"
            )
    if registered_in_metres(args.cameras) is False:  # a label the user chose, which would read as a measurement
        log.warning(
            "%s: register gave these cameras an arbitrary scale (its register_report.json: no --scale or --board): "
            "--units %s labels the exports, it does not make them %s (register with --scale A,B,METRES or --board "
            "for metres)",
            args.cameras,
            args.units,
            args.units,
        )
    export_points(args.out, args.cameras, args.units)
    print(f"wrote {args.out / 'points.trc'} and {args.out / 'points.c3d'}")  # noqa: T201
    return 0


def _add_run(subparsers: argparse._SubParsersAction) -> None:
    from dynrecon.pipeline import default_register
    from sfm.options import CameraMotion
    from tracking.options import TrackOptions

    parser = subparsers.add_parser(
        "run",
        help=COMMANDS["run"],
        description="Run every stage whose inputs changed since the last run in WS (WS/pipeline.json keeps "
        "their hashes): register (SfM, or --calibration imported) -> track (labels) -> subject (static videos "
        "the background left out, posed from the tracks) -> solve -> recording.rrd -> points3d.csv, points.trc, "
        "points.c3d.",
    )
    parser.add_argument("videos", nargs="+", type=Path, metavar="VIDEO")
    parser.add_argument("--out", type=out_path, required=True, metavar="WS", help="workspace folder")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--labels", type=Path, help="labels.csv to track (default: WS/labels.csv if present)")
    source.add_argument("--tracks", type=Path, help="ready 2D tracks (tracks.csv); no tracking")
    parser.add_argument("--skeleton", type=Path, help="skeleton JSON (points, connections) for the recording")
    parser.add_argument(
        "--max-frames",
        type=int,
        default=default_register().max_frames,
        help="SfM frames per video at most (the others are localized)",
    )
    parser.add_argument(
        "--track-window",
        type=int,
        default=TrackOptions().win_size,
        help="LK window side of the tracker, px (smaller for small markers)",
    )
    parser.add_argument(
        "--track-patch",
        type=int,
        default=TrackOptions().patch,
        help="appearance patch side of the tracker, px (smaller for small markers)",
    )
    parser.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="known intrinsics for registration (cameras.json, calib .toml or .qca); kept fixed",
    )
    parser.add_argument(
        "--scale",
        default=None,
        metavar="A,B,METRES",
        help="distance between two tracked points: the scale of static videos posed from the subject",
    )
    parser.add_argument(
        "--board",
        type=Path,
        default=None,
        help="ChArUco board file (charuco.toml) seen in the videos: intrinsics and scale of the static videos "
        "posed from the subject; without --tracks or labels its corners found in the videos are the tracks",
    )
    parser.add_argument(
        "--camera-motion",
        choices=[m.value for m in CameraMotion],
        default=CameraMotion.AUTO.value,
        help="registration: auto (measured per video), or static / moving for every video",
    )
    add_calibration_arguments(
        parser,
        "a lab calibration of static cameras (what `dynrecon import-calibration` reads: .toml, .qca.txt, .qca, "
        ".xml, .mat, DLT coefficients, cameras.json): imported instead of the SfM registration",
    )
    add_units_argument(parser)
    parser.add_argument("--force", action="store_true", help="redo every stage")
    parser.set_defaults(func=_run)


def add_units_argument(parser: argparse.ArgumentParser) -> None:
    """`--units` of `dynrecon run` and `dynrecon batch`."""
    parser.add_argument(
        "--units",
        default=None,
        help="unit label of the TRC/C3D exports (default: m when the world is metric: a calibration, --scale or "
        "--board; else mm, a nominal label of an arbitrary scale)",
    )


def add_calibration_arguments(parser: argparse.ArgumentParser, help_calibration: str) -> None:
    """`--calibration FILE` with import-calibration's `--format` and `--units` as `--calibration-format` and
    `--calibration-units` (`dynrecon run` and `dynrecon batch`)."""
    from sfm.cli import SYNCHRONIZED_HELP
    from sfm.options import OFFSETS_HELP, CalibrationFormat, DltPixels, RegisterOptions, Units, parse_offsets

    parser.add_argument("--calibration", type=Path, metavar="FILE", help=help_calibration)
    parser.add_argument(
        "--calibration-format",
        choices=[f.value for f in CalibrationFormat],
        default="auto",
        help="format of the calibration (default: from the file name), as import-calibration's --format",
    )
    parser.add_argument(
        "--calibration-units",
        choices=[u.value for u in Units],
        default="auto",
        help="unit of the calibration's TOML and DLT translations, as import-calibration's --units (default auto)",
    )
    parser.add_argument(
        "--calibration-pixels",
        choices=[p.value for p in DltPixels],
        default="auto",
        help="a DLT calibration's pixels, as import-calibration's --pixels (default auto)",
    )
    parser.add_argument(
        "--calibration-profile",
        type=Path,
        metavar="TXT",
        help="a DLT calibration's camera profile (the lenses), as import-calibration's --profile",
    )
    parser.add_argument(
        "--synchronized",
        action="store_true",
        help=f"{SYNCHRONIZED_HELP} (import-calibration's); without --calibration, register's subject path fits each "
        "pair of videos at offset 0 unless its tracks clearly prefer another",
    )
    parser.add_argument("--offsets", type=parse_offsets, default={}, metavar="NAME=S,...", help=OFFSETS_HELP)
    parser.add_argument(
        "--max-offset",
        type=positive_seconds,
        default=RegisterOptions().max_offset,
        metavar="SECONDS",
        help=f"how far apart (each way) register's subject path searches two videos' start times (default "
        f"{RegisterOptions().max_offset:g}): give more when the cameras were started further apart",
    )


def check_track_flags(args: argparse.Namespace) -> None:
    """`--track-window`, `--track-patch` and `--max-frames` of `run` and `batch`: a one-line error when unusable."""
    from dynrecon.errors import InputError
    from tracking.options import MAX_WINDOW

    for flag, value in (("--track-window", args.track_window), ("--track-patch", args.track_patch)):
        if not 5 <= value <= MAX_WINDOW:
            raise InputError(None, f"{flag} {value}: must be 5 to {MAX_WINDOW} px")
    if args.max_frames < 2:
        raise InputError(None, f"--max-frames {args.max_frames}: must be 2 or more")


def calibration_options(args: argparse.Namespace) -> ImportCalibrationOptions:
    """The import options `add_calibration_arguments` parsed."""
    from sfm.options import CalibrationFormat, DltPixels, ImportCalibrationOptions, Units

    return ImportCalibrationOptions(
        format=CalibrationFormat(args.calibration_format),
        units=Units(args.calibration_units),
        pixels=DltPixels(args.calibration_pixels),
        profile=args.calibration_profile,
        synchronized=args.synchronized,
        offsets=args.offsets,
    )


def _run(args: argparse.Namespace) -> int:
    from dynrecon.pipeline import run_stages
    from dynrecon.warnings_seen import warnings_seen

    options = pipeline_options(args)
    with warnings_seen() as seen:
        result = run_stages(args.videos, args.out, options)
    for stage in result.stages:
        print(f"{stage.name:9s} {'skipped (up to date)' if stage.skipped else f'{stage.seconds:.1f} s'}")  # noqa: T201
    if (result.workspace / "recording.rrd").is_file():
        print(f"open the recording with: rerun {result.workspace / 'recording.rrd'}")  # noqa: T201
    if seen.messages and not args.quiet:  # with -q the warnings were all there was to read
        print(f"{len(seen.messages)} warning(s) in the log above, once each:")  # noqa: T201
        for message in seen.messages:
            print(f"  - {message}")  # noqa: T201
    if result.next_step:
        print(f"next: {result.next_step}")  # noqa: T201
    return 0


def pipeline_options(args: argparse.Namespace) -> PipelineOptions:
    """`dynrecon run`'s parsed flags as the pipeline's options (a lab calibration replaces register's clock flags)."""
    from dynrecon.pipeline import PipelineOptions, default_register
    from sfm.options import CameraMotion
    from sfm.register_cli import parse_scale
    from tracking.options import TrackOptions

    scale = parse_scale(args.scale)
    check_track_flags(args)
    register = dataclasses.replace(
        default_register(),
        max_frames=args.max_frames,
        intrinsics=args.intrinsics,
        scale=scale,
        board=args.board,
        synchronized=args.synchronized and args.calibration is None,
        offsets=args.offsets if args.calibration is None else {},
        max_offset=args.max_offset,
        camera_motion=CameraMotion(args.camera_motion),
    )
    track = TrackOptions(win_size=args.track_window, patch=args.track_patch)
    options = PipelineOptions(
        register=register,
        track=track,
        labels=args.labels,
        tracks=args.tracks,
        skeleton=args.skeleton,
        calibration=args.calibration,
        calibration_options=calibration_options(args),
        units=args.units,
        force=args.force,
    )
    return options


def _add_demo(subparsers: argparse._SubParsersAction) -> None:
    from dynrecon import demo

    parser = subparsers.add_parser(
        "demo", help=COMMANDS["demo"], description=demo.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--out",
        type=out_path,
        default=Path("dynrecon-demo"),
        help="folder for the results (a fresh one is made beside it if it has results)",
    )
    parser.add_argument(
        "--simulated",
        action="store_true",
        help="simulated cameras instead of the videos: no registration or tracking (~30 s)",
    )
    parser.add_argument(
        "--sample",
        type=Path,
        default=demo.VIDEO_SAMPLE,
        help="a folder laid out like data_samples/video_sample (default: that one)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=demo.DemoOptions().sfm_threads,
        help="COLMAP threads of the registration (default -1: all cores; 1: the same cameras on "
        "every run, ~25 %% slower)",
    )
    parser.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    from dynrecon import demo

    started = time.perf_counter()
    result = demo.run(
        args.out, demo.DemoOptions(simulated=args.simulated, sample=args.sample, sfm_threads=args.threads)
    )
    seconds = time.perf_counter() - started
    if result.pipeline is None:
        print(  # noqa: T201
            f"demo (--simulated): 4 unsynchronized simulated cameras, walker sample, solved in {seconds:.0f} s"
        )
    else:
        stages = ", ".join(f"{s.name} {s.seconds:.0f} s" for s in result.pipeline.stages)
        print(  # noqa: T201
            f"demo: 3 unsynchronized handheld videos (30/24/20 fps) of the video sample, {seconds:.0f} s ({stages})"
        )
        print(  # noqa: T201
            "points moved into the sample's true frame by the similarity (scale, rotation, translation) that "
            "maps the registered cameras onto the true ones"
        )
    print(f"accuracy vs ground truth, {result.accuracy.count} points (mm): {result.accuracy.table()}")  # noqa: T201
    print(f"results in {result.workspace}")  # noqa: T201
    print(f"open the recording with: rerun {result.recording}")  # noqa: T201
    return 0
