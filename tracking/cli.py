"""Subcommands of the `tracking` stage: `track` (propagate labels) and `import-tracks` (other tools' points).

The `track` parser reads its defaults from the light `tracking.options`; `import-tracks` loads the importers (and
`dynrecon` builds both only when one of `COMMANDS` is chosen); the stages load in the handlers.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dynrecon.arguments import out_path

COMMANDS = {
    "track": "carry the labels of WS/labels.csv through every frame of the videos into WS/tracks.csv",
    "import-tracks": "import 2D points into tracks.csv: DeepLabCut, SLEAP, OpenPose, DLTdv / Argus, a plain "
    "video,frame,point,x,y CSV, or ChArUco board corners found in videos",
}


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register this stage's subcommands on the main parser."""
    _add_track(subparsers)
    _add_import(subparsers)


def _add_track(subparsers: argparse._SubParsersAction) -> None:
    from tracking.options import Blend, Method, TrackOptions

    defaults = TrackOptions()
    parser = subparsers.add_parser(
        "track",
        help=COMMANDS["track"],
        description="Headless version of the labeling page's 'track' button. Videos come from --videos, else "
        "WS/labeling.json, else WS/videos/*; a video's name is its file stem.",
    )
    parser.add_argument("workspace", type=Path, metavar="WS", help="workspace folder with labels.csv")
    parser.add_argument("--videos", type=Path, nargs="+", metavar="VIDEO", help="track only these videos")
    parser.add_argument("--out", type=out_path, help="output file (default WS/tracks.csv)")
    parser.add_argument(
        "--method",
        choices=[m.value for m in Method],
        default=defaults.method.value,
        help=f"step tracker (default {defaults.method.value})",
    )
    parser.add_argument(
        "--blend",
        choices=[b.value for b in Blend],
        default=defaults.blend.value,
        help=f"combining forward and backward tracks (default {defaults.blend.value})",
    )
    parser.add_argument(
        "--min-score",
        type=float,
        default=defaults.min_score,
        help=f"leave out tracked positions with a lower score (default {defaults.min_score})",
    )
    parser.add_argument(
        "--fb-threshold",
        type=float,
        default=defaults.fb_threshold,
        help=f"LK forward-backward error limit in pixels (default {defaults.fb_threshold})",
    )
    parser.add_argument(
        "--win-size",
        type=int,
        default=defaults.win_size,
        help=f"LK window side in pixels (default {defaults.win_size})",
    )
    parser.add_argument(
        "--no-closure-check",
        action="store_true",
        help="keep a track that reaches the point's next label far from it (by default its frames count only where "
        "the track from the other label confirms them: drift)",
    )
    parser.set_defaults(func=_run_track)


def _run_track(args: argparse.Namespace) -> int:
    from dynrecon.errors import InputError
    from tracking.options import MAX_WINDOW, Blend, Method, TrackOptions
    from tracking.stage import run

    if not args.workspace.is_dir():
        raise InputError(args.workspace, "workspace folder not found", fix="give the folder with labels.csv")
    if not 0.0 <= args.min_score <= 1.0:
        raise InputError(None, f"--min-score {args.min_score} is outside 0..1")
    if not args.fb_threshold > 0 or not 5 <= args.win_size <= MAX_WINDOW:
        raise InputError(None, f"--fb-threshold must be > 0 and --win-size from 5 to {MAX_WINDOW}")
    options = TrackOptions(
        method=Method(args.method),
        blend=Blend(args.blend),
        min_score=args.min_score,
        fb_threshold=args.fb_threshold,
        win_size=args.win_size,
        closure_check=not args.no_closure_check,
    )
    path = run(args.workspace, args.out, options, videos=args.videos)
    print(path)  # noqa: T201
    return 0


def _add_import(subparsers: argparse._SubParsersAction) -> None:
    from tracking.importing import Format
    from tracking.pixels import DltPixels

    parser = subparsers.add_parser(
        "import-tracks",
        help=COMMANDS["import-tracks"],
        description="Rows of other videos and manual labels already in the output are kept; the imported "
        "videos' other rows are replaced.",
    )
    parser.add_argument(
        "inputs",
        type=Path,
        nargs="+",
        metavar="INPUT",
        help="DLC .csv or .h5, SLEAP .slp or analysis .h5, OpenPose JSON file or folder, DLTdv / Argus "
        "*xypts.csv, plain .csv, or a video (with --board)",
    )
    parser.add_argument("--out", type=out_path, required=True, help="tracks.csv to write (e.g. WS/tracks.csv)")
    parser.add_argument(
        "--format",
        choices=[f.value for f in Format],
        default="auto",
        help="input format (default: detected from the file)",
    )
    parser.add_argument(
        "--video",
        help="the video the input's detections belong to: its name or file (cam1 or videos/cam1.mp4 both name "
        "cam1; default: from the input's file name)",
    )
    parser.add_argument(
        "--videos",
        type=Path,
        nargs="+",
        default=[],
        metavar="VIDEO",
        help="DLTdv / Argus points: the videos of cam1, cam2, ... in order (they name the videos, and their heights "
        "turn rows counted from the bottom into image rows; default names cam1, cam2, ...)",
    )
    parser.add_argument(
        "--pixels",
        choices=[p.value for p in DltPixels],
        default="auto",
        help="DLTdv / Argus points: the tool's pixels, dltdv7 (DLTdv 5-7: rows up from the bottom), dltdv8, argus "
        "or opencv (default: argus for Argus's columns, dltdv8 for DLTdv 8.4's _U/_V; DLTdv's _X/_Y need it)",
    )
    parser.add_argument("--map", default="", metavar="OLD=NEW,...", help="rename points, e.g. nose=head,Neck=neck")
    parser.add_argument("--drop-unmapped", action="store_true", help="with --map, keep only the mapped points")
    parser.add_argument(
        "--min-score", type=float, default=0.0, help="leave out detections with a lower confidence (default 0)"
    )
    parser.add_argument(
        "--person",
        metavar="N|all",
        help="OpenPose's people (linked through the frames), DeepLabCut's individuals or SLEAP's tracks, numbered "
        "by how much they are seen: import person N (OpenPose's default 0, the one seen most; DeepLabCut's and "
        "SLEAP's default: each under its own name) or all (points person<N>_<keypoint>, matched across videos by "
        "register)",
    )
    parser.add_argument(
        "--board",
        type=Path,
        metavar="TOML",
        help="ChArUco (videos as inputs): caliscope's charuco.toml or config.toml; points are "
        "the board's inner corners corner_<id>",
    )
    parser.set_defaults(func=_run_import)


def _video_name(value: str | None) -> str | None:
    """--video's name (dynrecon.names.video_name)."""
    from dynrecon.names import video_name

    return None if value is None else video_name(value)


def _run_import(args: argparse.Namespace) -> int:
    from dynrecon.errors import InputError
    from tracking.importing import Format, ImportOptions, parse_mapping, run_import
    from tracking.pixels import DltPixels

    every_person = args.person is not None and args.person.strip().lower() == "all"
    if args.person is not None and not every_person and not (args.person.strip().isdigit() and args.person.isascii()):
        raise InputError(None, f"--person {args.person}: expected a number 0, 1, ... or all")
    if args.video is not None and len(args.inputs) > 1:
        raise InputError(
            args.inputs[1],
            f"--video {args.video} names one video, but {len(args.inputs)} inputs were given",
            fix="import each video's file with its own --video, or leave --video out (names from the file names)",
        )
    if not 0.0 <= args.min_score <= 1.0:  # NaN too
        raise InputError(None, f"--min-score {args.min_score} is outside 0..1")
    options = ImportOptions(
        format=Format(args.format),
        video=_video_name(args.video),
        mapping=parse_mapping(args.map),
        drop_unmapped=args.drop_unmapped,
        min_score=args.min_score,
        person=None if every_person or args.person is None else int(args.person),
        every_person=every_person,
        board=args.board,
        videos=args.videos,
        pixels=DltPixels(args.pixels),
    )
    path = run_import(args.inputs, args.out, options)
    print(path)  # noqa: T201
    return 0
