"""The `dynrecon register` subcommand: a thin layer over `sfm.register` (`sfm.stage.run`).

Imports only `sfm.options` to build the parser, so that `dynrecon --help` does not load pycolmap or OpenCV.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from dynrecon.arguments import frame_rates, image_size, out_path, positive_seconds

if TYPE_CHECKING:
    from sfm.options import RegisterOptions


def add_register_command(subparsers: argparse._SubParsersAction) -> None:
    """Register `dynrecon register` on the main parser."""
    from sfm.options import RegisterOptions

    defaults = RegisterOptions()
    parser = subparsers.add_parser(
        "register",
        help="SfM on the static background: a pose for every frame of every video (cameras.json)",
        description="Registers unsynchronized videos and writes WS/cameras.json, WS/background.ply and "
        "WS/register_report.json. Each video's camera is tested for motion: a static one sends one background "
        "image to SfM and all its frames share its pose; a moving one sends sampled frames and the others are "
        "posed by PnP. Static videos the background cannot pose are posed from the moving subject's 2D tracks "
        "(WS/tracks.csv or --tracks), which also mask the subject out of SfM. The report says which path posed "
        "each video.",
    )
    parser.add_argument("videos", type=Path, nargs="+", metavar="VIDEO")
    parser.add_argument("--out", type=out_path, required=True, metavar="WS", help="workspace folder")
    _add_frame_arguments(parser.add_argument_group("frames for SfM"), defaults)
    _add_sfm_arguments(parser.add_argument_group("features, matching, mapping"), defaults)
    _add_static_arguments(parser.add_argument_group("static cameras and the subject path"), defaults)
    _add_mask_arguments(parser.add_argument_group("masks and localization"), defaults)
    parser.add_argument(
        "--threads",
        type=int,
        default=defaults.num_threads,
        help="COLMAP's threads, -1: all cores; 1: one core (nothing else runs beside either)",
    )
    parser.set_defaults(func=_run_register)


def _add_frame_arguments(frames: argparse._ArgumentGroup, defaults: RegisterOptions) -> None:
    from sfm.options import KeyframeSelection

    frames.add_argument(
        "--keyframes-by",
        choices=[m.value for m in KeyframeSelection],
        default=defaults.keyframes_by.value,
        help="content: a new SfM frame where the view has moved enough; even: --step / --time-step, thinned",
    )
    frames.add_argument(
        "--keyframe-motion",
        type=float,
        default=defaults.keyframe_motion,
        help="content: median corner motion since the last keyframe, as a share of the long side",
    )
    frames.add_argument(
        "--keyframe-survival",
        type=float,
        default=defaults.keyframe_survival,
        help="content: a new keyframe when fewer than this share of the last one's corners are still tracked",
    )
    frames.add_argument(
        "--step", type=int, default=defaults.step, help="every Nth decoded frame (0: all); implies even"
    )
    frames.add_argument(
        "--time-step", type=float, default=None, help="or one frame per this many seconds; implies even"
    )
    frames.add_argument("--max-frames", type=int, default=defaults.max_frames, help="SfM frames per video, at most")
    frames.add_argument("--long-side", type=int, default=defaults.long_side, help="resize frames to this (px)")


def _add_sfm_arguments(sfm: argparse._ArgumentGroup, defaults: RegisterOptions) -> None:
    from sfm.options import Mapper

    sfm.add_argument("--max-features", type=int, default=defaults.max_features, help="SIFT features per frame")
    sfm.add_argument("--max-ratio", type=float, default=defaults.max_ratio, help="SIFT ratio test")
    sfm.add_argument(
        "--overlap",
        type=int,
        default=defaults.sequential_overlap,
        help="sequential pairs within a video: i with i+1..i+OVERLAP",
    )
    sfm.add_argument(
        "--keyframes",
        type=int,
        default=defaults.keyframes,
        help="evenly spaced SfM frames per video matched with those of every other video",
    )
    sfm.add_argument(
        "--cross-partners",
        type=int,
        default=defaults.cross_partners,
        help="every SfM frame is also matched with its N most similar frames of each other video (0: off)",
    )
    sfm.add_argument(
        "--init-min-inliers",
        type=int,
        default=defaults.init_min_inliers,
        help="inliers the mapper needs for its initial pair (lower for wide baselines)",
    )
    sfm.add_argument("--mapper", choices=[m.value for m in Mapper], default=defaults.mapper.value)
    sfm.add_argument(
        "--camera-model",
        default=defaults.camera_model,
        help="COLMAP camera model (SIMPLE_RADIAL, RADIAL, OPENCV, PINHOLE, ...)",
    )
    sfm.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="known intrinsics (cameras.json, calib .toml or .qca); kept fixed",
    )
    sfm.add_argument(
        "--background-features",
        type=int,
        default=defaults.background_features,
        help="SIFT features of a static video's background image",
    )


def _add_static_arguments(static: argparse._ArgumentGroup, defaults: RegisterOptions) -> None:
    from sfm.options import CameraMotion, SubjectPath, parse_offsets

    static.add_argument(
        "--camera-motion",
        choices=[m.value for m in CameraMotion],
        default=defaults.camera_motion.value,
        help="auto: measured per video; static / moving: for every video",
    )
    static.add_argument(
        "--subject",
        choices=[m.value for m in SubjectPath],
        default=defaults.subject.value,
        help="pose static videos from the subject's tracks: auto (those the background left out), always, never",
    )
    static.add_argument(
        "--scale",
        default=None,
        metavar="A,B,METRES",
        help="the distance between two tracked points, for the subject path's scale without background anchors",
    )
    static.add_argument(
        "--synchronized",
        action="store_true",
        help="the videos were recorded on one clock (a triggered rig): the subject path fits each pair at offset 0 "
        "unless its tracks clearly prefer another (the report says which pairs contradict it)",
    )
    static.add_argument(
        "--offsets",
        type=parse_offsets,
        default={},
        metavar="NAME=S,...",
        help="known clock offsets in seconds per video (global time = own time + offset: a clap, a timecode), "
        "e.g. cam1=0,cam2=0.033: the subject path fits each pair at them unless its tracks clearly prefer another, "
        "and cameras.json carries them where it found no clock, for the solve to test",
    )
    static.add_argument(
        "--max-offset",
        type=positive_seconds,
        default=defaults.max_offset,
        metavar="SECONDS",
        help=f"how far apart (each way) the subject path searches two videos' start times (default "
        f"{defaults.max_offset:g}): give more when the cameras were started further apart",
    )
    static.add_argument(
        "--board",
        type=Path,
        default=None,
        metavar="CHARUCO_TOML",
        help="a ChArUco board (caliscope charuco.toml / config.toml) seen in the videos: the subject path's "
        "intrinsics (videos without --intrinsics) and scale; without tracks its corners are found in the videos "
        "(written to WS/tracks.csv)",
    )
    static.add_argument(
        "--no-markers",
        action="store_true",
        help="without tracks, do not take the corners of ArUco / AprilTag markers in view as the subject's tracks "
        "(by default they pose the static videos the background left out; written to WS/marker_tracks.csv)",
    )


def _add_mask_arguments(masks: argparse._ArgumentGroup, defaults: RegisterOptions) -> None:
    from sfm.options import InBetween, Localize

    masks.add_argument(
        "--tracks",
        type=Path,
        default=None,
        help="tracks.csv: the subject path's tracks and the masks' (default: WS/tracks.csv)",
    )
    masks.add_argument(
        "--fps",
        type=frame_rates,
        metavar="FPS|NAME=FPS,...",
        default=None,
        help="the frame rate of videos that are not here (2D tracks shared without them): each VIDEO that is no file "
        "is a name, its frames those of the tracks of that name; such a camera is taken as static and posed from "
        "the subject's tracks; one rate, or one per video (cam0=59.94,cam1=30)",
    )
    masks.add_argument(
        "--size",
        type=image_size,
        default=None,
        metavar="WxH",
        help="with --fps: the missing videos' image size (default: their cameras' size in --intrinsics)",
    )
    masks.add_argument(
        "--masks",
        type=Path,
        default=None,
        help="folder of masks: DIR/<video>/<frame:06d>.png or DIR/<video>.png, black = ignore",
    )
    masks.add_argument(
        "--mask-radius", type=float, default=defaults.mask_radius, help="pixels masked around tracked points"
    )
    masks.add_argument("--no-masks", action="store_true", help="do not mask anything")
    masks.add_argument(
        "--localize",
        choices=[m.value for m in Localize],
        default=defaults.localize.value,
        help="frames posed by PnP besides the SfM frames (auto: tracked frames, else all)",
    )
    masks.add_argument(
        "--inbetween",
        choices=[m.value for m in InBetween],
        default=defaults.inbetween.value,
        help="pose the localized frames by tracking the keyframes' features (SIFT where it fails), or by SIFT",
    )
    masks.add_argument("--min-inliers", type=int, default=defaults.min_inliers, help="PnP inliers needed")


def parse_scale(text: str | None) -> tuple[str, str, float] | None:
    """`A,B,METRES` -> (A, B, metres); a one-line error otherwise."""
    from dynrecon.errors import InputError

    if text is None:
        return None
    parts = text.split(",")
    try:
        metres = float(parts[2]) if len(parts) == 3 else float("nan")
    except ValueError:
        metres = float("nan")
    if len(parts) != 3 or not parts[0] or not parts[1] or not metres > 0 or metres == float("inf"):
        raise InputError(
            None, f"--scale {text!r} is not POINT_A,POINT_B,METRES", fix="e.g. --scale l_knee,l_ankle,0.42"
        )
    return parts[0], parts[1], metres


def _run_register(args: argparse.Namespace) -> int:
    from sfm.options import CameraMotion, InBetween, KeyframeSelection, Localize, Mapper, RegisterOptions, SubjectPath
    from sfm.stage import run

    options = RegisterOptions(
        keyframes_by=KeyframeSelection(args.keyframes_by),
        keyframe_motion=args.keyframe_motion,
        keyframe_survival=args.keyframe_survival,
        step=args.step,
        time_step=args.time_step,
        max_frames=args.max_frames,
        long_side=args.long_side,
        max_features=args.max_features,
        background_features=args.background_features,
        camera_motion=CameraMotion(args.camera_motion),
        subject=SubjectPath(args.subject),
        scale=parse_scale(args.scale),
        synchronized=args.synchronized,
        offsets=args.offsets,
        max_offset=args.max_offset,
        board=args.board,
        find_markers=not args.no_markers,
        max_ratio=args.max_ratio,
        sequential_overlap=args.overlap,
        keyframes=args.keyframes,
        cross_partners=args.cross_partners,
        mapper=Mapper(args.mapper),
        camera_model=args.camera_model,
        intrinsics=args.intrinsics,
        tracks=args.tracks,
        fps=args.fps,
        size=args.size,
        masks=args.masks,
        mask_radius=args.mask_radius,
        use_masks=not args.no_masks,
        localize=Localize(args.localize),
        inbetween=InBetween(args.inbetween),
        min_inliers=args.min_inliers,
        init_min_inliers=args.init_min_inliers,
        num_threads=args.threads,
    )
    path = run(args.videos, args.out, options)
    report = json.loads((Path(args.out) / "register_report.json").read_text(encoding="utf-8"))
    for video in report["videos"]:
        # a video left unposed for one reason says it here; several reasons are the report's to list
        reasons = {run["reason"] for run in video["failed"]} if not video["registered"] else set()
        why = f"; {next(iter(reasons))}" if len(reasons) == 1 else ""
        total = video.get("frames_in_video")
        # with tracks only their frames are wanted: a count of wanted frames alone read as the whole video
        of = (
            f" of {total} in the video (--localize all poses the others)"
            if total and total > video["frames_given"]
            else ""
        )
        print(  # noqa: T201
            f"{video['name']}: {video['registered']}/{video['frames_given']} frames registered{of} "
            f"({video['camera']} camera; posed by {video['posed_by']}{why})"
        )
    print(path)  # noqa: T201
    return 0
