"""Subcommands of the `sfm` stage: `register` (SfM) and `import-calibration` (static calibrated cameras).

The parsers are built from `sfm.options` only; the stages are imported when a command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dynrecon.arguments import frame_rates, image_size, out_path


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register this stage's subcommands on the main parser."""
    _add_import(subparsers)
    _add_register(subparsers)


def _add_import(subparsers: argparse._SubParsersAction) -> None:
    from sfm.options import OFFSETS_HELP, CalibrationFormat, DltPixels, Units, parse_offsets

    parser = subparsers.add_parser(
        "import-calibration",
        help="write cameras.json from a lab calibration of static cameras: Qualisys .qca, Pose2Sim / anipose / "
        "FreeMoCap / caliscope .toml, DANNCE .mat, DLTdv / easyWand / Argus DLT coefficients, or another "
        "recording's cameras.json",
        description="Every decoded frame of each video gets its calibrated camera's static pose. Cameras are "
        "matched to videos by name (cam01.mp4 <-> cam_01, minimal_back.mp4 <-> back; caliscope's cam_id 0 is cam_0), "
        "else in the given order. "
        "TOML rotations may be Rodrigues vectors or 3x3 matrices (cam_from_world, OpenCV).",
    )
    parser.add_argument(
        "calibration",
        type=Path,
        help="calibration file (.qca.txt / .qca / .xml, or .toml: Pose2Sim/anipose/FreeMoCap [cam_N], "
        "caliscope [cameras.N] or [cam_N]; DANNCE/Label3D: a *_dannce.mat, or a folder of cam*_params.mat; or "
        "the cameras.json of another recording by the same static cameras, e.g. a board filmed before the session; "
        "or DLT coefficients: DLTdv/easyWand *_dltCoefs.csv, easyWand's *_easyWandData.mat, Argus "
        "*-dlt-coefficients.csv)",
    )
    parser.add_argument(
        "videos",
        type=Path,
        nargs="+",
        metavar="VIDEO",
        help="the videos, one per camera; with --fps, a video that is not here may be given by its name",
    )
    parser.add_argument("--out", type=out_path, required=True, metavar="WS", help="workspace folder for cameras.json")
    parser.add_argument(
        "--format",
        choices=[f.value for f in CalibrationFormat],
        default="auto",
        help="calibration format (default: from the file name; toml covers every TOML layout)",
    )
    parser.add_argument(
        "--units",
        choices=[u.value for u in Units],
        default="auto",
        help="unit of TOML and DLT translations (default auto: mm when [metadata] gives the board's square in mm, "
        "as FreeMoCap's and sleap-anipose's do, or the cameras are over 100 units apart; else m; DANNCE's: mm)",
    )
    parser.add_argument(
        "--pixels",
        choices=[p.value for p in DltPixels],
        default="auto",
        help="a DLT file's pixels: dltdv7 (DLTdv 5-7 and easyWand: rows up from the bottom), dltdv8, argus, or "
        "opencv (default auto: argus for Argus's file names, else DLTdv's; rows up from the bottom where that "
        "makes the world right-handed)",
    )
    parser.add_argument(
        "--profile",
        type=Path,
        metavar="TXT",
        help="a DLT file's camera profile (easyWand / Argus / DLTdv: a row 'cam# f W H cx cy aspect k1 k2 t1 t2 k3' "
        "per camera): the lenses' distortion, which the DLT coefficients leave out",
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="multiply world coordinates (metres) by this factor (default 1)",
    )
    parser.add_argument("--synchronized", action="store_true", help=SYNCHRONIZED_HELP)
    parser.add_argument(
        "--offsets",
        type=parse_offsets,
        default={},
        metavar="NAME=S,...",
        help=OFFSETS_HELP,
    )
    parser.add_argument(
        "--fps",
        type=frame_rates,
        metavar="FPS|NAME=FPS,...",
        help="the frame rate of videos that are not here (a calibration and 2D tracks shared without them): each "
        "VIDEO that is no file is a name, its frames those of the tracks (--tracks) of that name; one rate, or one "
        "per video (cam0=59.94,cam1=30)",
    )
    parser.add_argument(
        "--tracks",
        type=Path,
        metavar="CSV",
        help="with --fps: the tracks.csv whose frames stand for the missing videos' (default: WS/tracks.csv)",
    )
    parser.add_argument(
        "--size",
        type=image_size,
        metavar="WxH",
        help="with --fps: the missing videos' image size (default: their cameras' calibrated size)",
    )
    parser.set_defaults(func=_run_import)


SYNCHRONIZED_HELP = (
    "the videos were recorded on one clock (a triggered rig, frame i of each at the same instant): each video's "
    "clock_offset is 0 in cameras.json, which the solve tests against the clocks it recovers and keeps if it fits"
)


def _run_import(args: argparse.Namespace) -> int:
    from dynrecon.errors import InputError
    from sfm.calibration import run
    from sfm.options import CalibrationFormat, DltPixels, ImportCalibrationOptions, Units

    if Path(args.calibration).resolve() == (Path(args.out) / "cameras.json").resolve():
        # written over, the user's file would lose what the import does not carry (its clock offsets)
        raise InputError(args.calibration, "is the cameras.json this import would write", fix="give another --out")
    path = run(
        args.calibration,
        args.videos,
        args.out,
        ImportCalibrationOptions(
            format=CalibrationFormat(args.format),
            units=Units(args.units),
            pixels=DltPixels(args.pixels),
            profile=args.profile,
            scale=args.scale,
            synchronized=args.synchronized,
            offsets=args.offsets,
            fps=args.fps,
            tracks=args.tracks,
            size=args.size,
        ),
    )
    print(path)  # noqa: T201
    return 0


def _add_register(subparsers: argparse._SubParsersAction) -> None:
    """Filled in by sfm.register_cli to keep this file small."""
    from sfm.register_cli import add_register_command

    add_register_command(subparsers)
