"""The subject path of `register`: static videos posed from the moving subject's 2D tracks (`sfm.subject`).

Used for the static videos the background left out (or for every static video on request). Videos that the
background posed anchor the world frame and its scale; without them the scale comes from `--scale A,B,METRES`,
or the report says that the units are arbitrary.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pycolmap

from sfm.board import board_scale, calibrate_from_board
from sfm.options import RegisterOptions, SubjectPath
from sfm.plan import FramePose, VideoPlan
from sfm.subject import SubjectCalibrationError, SubjectOptions, SubjectResult, SubjectVideo, calibrate_from_subject
from sfm.subject.observations import select_rows
from sfm.subject.stability import Stability, check_stability
from tracking.charuco import read_charuco_board
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def _posed(results: dict[int, FramePose]) -> FramePose | None:
    return next((r for r in results.values() if r.pose is not None), None)


def pose_from_subject(
    videos: list[VideoPlan],
    results: dict[str, dict[int, FramePose]],
    tracks: Tracks | None,
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]],
    options: RegisterOptions,
    warnings: list[str],
) -> dict[str, Any] | None:
    """Pose the static videos that need it from the tracks; updates `results` in place. Returns the report's
    `subject` section (None when the path was not tried)."""
    static = [v for v in videos if v.static]
    unposed = [v for v in static if _posed(results[v.info.name]) is None]
    if options.subject is SubjectPath.NEVER or not static:
        return None
    if options.subject is SubjectPath.AUTO and not unposed:
        return None
    if tracks is None:
        if unposed:
            warnings.append(
                f"static videos {', '.join(v.info.name for v in unposed)} were not posed by the background; "
                "2D tracks of the moving subject can pose them: run `dynrecon track WS` (or import-tracks) "
                "and register again"
            )
        return {
            "used": False,
            "why": "no 2D tracks of the moving subject (WS/tracks.csv or --tracks): track it (dynrecon track WS, or "
            "import-tracks) and register again",
        }
    board: dict[str, Any] | None = None
    scale = options.scale
    moving_posed = any(not v.static and _posed(results[v.info.name]) is not None for v in videos)
    anchors_allowed = options.subject is SubjectPath.AUTO or moving_posed
    if options.board is not None:
        # an anchor keeps the intrinsics its background pose was found with
        anchored = {v.info.name for v in static if anchors_allowed and _posed(results[v.info.name]) is not None}
        intrinsics, scale, board = _with_board(tracks, static, intrinsics, anchored, options, warnings)
    inputs, anchors = _subject_videos(static, set(tracks.video_names()), results, intrinsics, anchors_allowed)
    if len(inputs) < 2:
        return {
            "used": False,
            "why": f"tracks cover only {len(inputs)} static video(s); the subject path needs 2",
            "board": board,
        }
    names = {v.name for v in inputs}
    subject_tracks = select_rows(tracks, np.array([v in names for v in tracks.video], dtype=bool))
    subject_options = SubjectOptions(scale=scale)
    try:
        result = calibrate_from_subject(subject_tracks, inputs, subject_options)
        stability = check_stability(subject_tracks, inputs, result, subject_options)
    except SubjectCalibrationError as error:
        warnings.append(f"subject path: {error}")
        for video in unposed:
            for frame in results[video.info.name]:
                results[video.info.name][frame] = FramePose(pose=None, reason=f"subject path: {error}")
        return {"used": False, "why": str(error), "anchors": anchors, "board": board}
    if not stability.checked:
        warnings.append(f"subject path: poses unverified ({stability.why_unchecked})")
    posed = _apply(result, stability, anchors, {v.info.name: v for v in videos}, results, warnings)
    metric = result.metric or bool(anchors)
    if not metric:
        warnings.append(
            "subject path without background anchors or --scale: the units are arbitrary "
            "(give --scale POINT_A,POINT_B,METRES)"
        )
    log.info("subject path posed %s (anchors: %s)", ", ".join(posed) or "nothing", ", ".join(anchors) or "none")
    return {**_report(result, stability, posed, anchors, metric), "board": board}


def _with_board(
    tracks: Tracks,
    static: list[VideoPlan],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]],
    anchored: set[str],
    options: RegisterOptions,
    warnings: list[str],
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray | None]], tuple[str, str, float] | None, dict[str, Any]]:
    """`--board`: intrinsics from the board's views for the static videos without given ones (and not `anchored`
    by the background), and the scale from its corner spacing unless --scale was given. Returns (intrinsics,
    scale, the report's `board` section)."""
    assert options.board is not None
    board = read_charuco_board(options.board)
    tracked = set(tracks.video_names())
    names = [v.info.name for v in static if v.info.name in tracked]
    if not any(str(p).startswith("corner_") for p in tracks.point_names()):
        warnings.append(
            f"--board {options.board}: the tracks have no board corners (corner_<id> points): import them with "
            "`dynrecon import-tracks VIDEO... --board FILE`; the board was not used"
        )
        return intrinsics, options.scale, {"file": str(options.board), "used": False, "why": "no corner_<id> tracks"}
    merged = dict(intrinsics)
    cameras = []
    for video in static:
        name = video.info.name
        if name not in tracked or name in intrinsics or name in anchored:
            continue
        found = calibrate_from_board(tracks, name, (video.info.width, video.info.height), board)
        cameras.append(found.to_json())
        if found.used and found.K is not None:
            merged[name] = (found.K, found.dist)
            log.info("%s: intrinsics from %d board views (rms %.2f px)", name, found.views, found.rms_px or 0.0)
        else:
            warnings.append(f"{name}: intrinsics not taken from the board: {found.why}")
    scale = options.scale if options.scale is not None else board_scale(tracks, names, board)
    if options.scale is None and scale is None:
        warnings.append("--board: no two board corners are seen together in two videos: no scale from the board")
    section = {
        "file": str(options.board),
        "used": True,
        "cameras": cameras,
        "scale": None if options.scale is not None or scale is None else [scale[0], scale[1], round(scale[2], 6)],
    }
    return merged, scale, section


def _subject_videos(
    static: list[VideoPlan],
    tracked: set[str],
    results: dict[str, dict[int, FramePose]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]],
    anchors_allowed: bool,
) -> tuple[list[SubjectVideo], list[str]]:
    """The tracked static videos as the subject path's inputs, with the background's pose (an anchor) and
    intrinsics where it has them; returns the inputs and the anchors' names."""
    inputs = []
    anchors = []
    for video in static:
        name = video.info.name
        if name not in tracked:
            continue
        known = _posed(results[name]) if anchors_allowed else None
        K, dist = intrinsics.get(name, (None, None))
        if K is None and known is not None and known.intrinsics is not None:
            K, dist = known.intrinsics
        pose = None
        if known is not None and known.pose is not None:
            pose = (known.pose.rotation.matrix(), np.asarray(known.pose.translation))
            anchors.append(name)
        inputs.append(
            SubjectVideo(
                name=name,
                width=video.info.width,
                height=video.info.height,
                times=video.info.times,
                K=K,
                dist=dist,
                cam_from_world=pose,
            )
        )
    return inputs, anchors


def _apply(
    result: SubjectResult,
    stability: Stability,
    anchors: list[str],
    by_name: dict[str, VideoPlan],
    results: dict[str, dict[int, FramePose]],
    warnings: list[str],
) -> list[str]:
    """Every wanted frame of a camera the subject path posed (and the data determine) takes its pose; the others
    say why not. Returns the names of the posed videos."""
    posed = []
    for camera in result.cameras:
        if camera.name in anchors:
            continue
        if camera.name in stability.unstable:
            reason = f"subject path: {stability.unstable[camera.name]}"
            warnings.append(f"{camera.name}: {reason}")
            results[camera.name] = {int(f): FramePose(pose=None, reason=reason) for f in by_name[camera.name].wanted}
            continue
        frame_pose = FramePose(
            pose=pycolmap.Rigid3d(pycolmap.Rotation3d(camera.R), np.asarray(camera.t, dtype=float)),
            source="subject",
            intrinsics=(camera.K, camera.dist),
            error=camera.residual_px,
            inliers=camera.inliers,
        )
        results[camera.name] = {int(f): frame_pose for f in by_name[camera.name].wanted}
        posed.append(camera.name)
    for name, reason in result.failed.items():
        if name in results and _posed(results[name]) is None:
            results[name] = {f: FramePose(pose=None, reason=f"subject path: {reason}") for f in results[name]}
    return posed


def _report(
    result: SubjectResult, stability: Stability, posed: list[str], anchors: list[str], metric: bool
) -> dict[str, Any]:
    """The report's `subject` section after a calibration."""
    return {
        "used": True,
        "posed": posed,
        "anchors": anchors,
        "metric": metric,
        "cameras": [
            {
                "name": c.name,
                "offset_s": round(float(c.offset), 6),
                "inliers": int(c.inliers),
                "residual_px": round(float(c.residual_px), 3),
            }
            for c in result.cameras
        ],
        "pairs": [
            {
                "videos": [p.a, p.b],
                "offset_s": round(float(p.offset), 6),
                "inliers": int(p.inliers),
                "shared": int(p.shared),
                "runner_up_ratio": round(float(p.runner_up_ratio), 3),
                "degenerate": p.degenerate,
            }
            for p in result.pairs
        ],
        "failed": result.failed,
        "lens": result.lens.value,
        "lens_check": result.lens_check,
        "stability": stability.to_json(),
    }
