"""The subject path of `register`: static videos posed from the moving subject's 2D tracks (`sfm.subject`).

Used for the static videos the background left out (or for every static video on request). Videos that the
background posed anchor the world frame and its scale; without them the scale comes from `--scale A,B,METRES`,
or the report says that the units are arbitrary.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np
import pycolmap

from sfm.board import MIN_VIEWS, SCALE_FRAMES, BoardIntrinsics, board_scale, calibrate_from_board
from sfm.board_hint import board_hint
from sfm.options import RegisterOptions, SubjectPath
from sfm.plan import FramePose, VideoPlan
from sfm.register_posed import posed_video
from sfm.subject import SubjectCalibrationError, SubjectOptions, SubjectResult, SubjectVideo, choose_noise
from sfm.subject.model import UNPAIRED, UNTESTED, ScalePointsError, reasons_text
from sfm.subject.noise import choose_scale
from sfm.subject.posed import Alignment
from sfm.subject.posed_bundle import solve_with_posed
from sfm.subject.set_aside import largest_determined
from sfm.subject.stability import TWO_SELF_CALIBRATED, Stability, check_stability, pair_without_intrinsics
from tracking.charuco import board_corner_positions, read_charuco_board
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

# what to do without tracks; `dynrecon run` says its own options instead (dynrecon.pipeline)
TRACK_ADVICE = (
    "label the subject on a few frames (dynrecon label WS --videos VIDEO...) and track it (dynrecon track WS), or "
    "import a detector's tracks (dynrecon import-tracks), and register again"
)
UNCERTAIN_DEG = 2.0  # a posed camera the folds turn by more than this is reported as uncertain (a warning)


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
    if options.subject is SubjectPath.NEVER or not static or (options.subject is SubjectPath.AUTO and not unposed):
        if options.board is not None:
            if not static:
                why = "no static video"
            elif options.subject is SubjectPath.NEVER:
                why = "--subject never"
            else:
                why = "the background posed every static video (--subject always poses them from the board)"
            warnings.append(f"--board {options.board}: not used: {why}")
        return None
    if tracks is None:
        hint = board_hint([v.info.path for v in unposed]) if unposed and options.find_markers else None
        then = f"; {hint}" if hint else ""
        nothing_posed = all(_posed(frames) is None for frames in results.values())
        two_only = len(videos) == 2 and len(unposed) == 2  # a third video (a moving one too) may fix the focals
        if nothing_posed and two_only and any(v.info.name not in intrinsics for v in unposed):
            # the tracks alone would be refused a minute later (TWO_SELF_CALIBRATED): say both things at once
            then += "; two static videos also need their intrinsics (--intrinsics FILE) or a third video"
        if unposed:
            warnings.append(
                f"static videos {', '.join(v.info.name for v in unposed)} were not posed by the background; "
                f"2D tracks of the moving subject can pose them: {TRACK_ADVICE}{then}"
            )
        return {
            "used": False,
            "why": f"no 2D tracks of the moving subject (WS/tracks.csv or --tracks): {TRACK_ADVICE}{then}",
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
        why = f"tracks cover only {len(inputs)} static video(s); the subject path needs 2"
        tracked, static_names = sorted(tracks.video_names()), sorted(v.info.name for v in static)
        if not set(tracked) & set(static_names):
            why += (
                f" (the tracks' videos {', '.join(tracked[:6])} are none of the static videos "
                f"{', '.join(static_names[:6])})"
            )
        warnings.append(f"subject path: {why}")
        return {"used": False, "why": why, "board": board}
    names = {v.name for v in inputs}
    others = sorted(n for n, frames in results.items() if n not in names and _posed(frames) is not None)
    # fewer than two static anchors beside other posed videos: the posed videos' tracks give the frame and scale
    posed_tracked = sorted(set(others) & set(tracks.video_names()))
    by_posed = len(anchors) < 2 and bool(others)
    if by_posed and not posed_tracked:
        # the subject path's cameras need the background's frame and scale; without a tracked posed video they
        # would not match the background's other cameras (a silently inconsistent world)
        if anchors:
            why = (
                f"one static video the background posed ({anchors[0]}) fixes the subject path's frame but not its "
                f"scale against the background's other cameras ({', '.join(others)})"
            )
        else:
            why = (
                "no tracked video the background posed anchors the subject path in the background's world: its "
                f"cameras would have another frame and scale than the background's ({', '.join(others)})"
            )
        warnings.append(
            f"subject path: {why}; track the subject in a video the background posed (a handheld one, or two static "
            "ones), or register the static videos without the others"
        )
        return _refuse(unposed, results, why, {"used": False, "why": why, "anchors": anchors, "board": board})
    if not by_posed and not anchors and pair_without_intrinsics(inputs):
        # refused before any solve: the folds would refuse the pair (stability.check_stability), a minute later
        why = f"{' and '.join(sorted(names))}: {TWO_SELF_CALIBRATED}"
        warnings.append(f"subject path: {why}")
        return _refuse(unposed, results, why, {"used": False, "why": why, "anchors": anchors, "board": board})
    subject_tracks = tracks.of_videos(names)
    # a triggered rig (every static video on one clock) or known offsets: a claim each pair's tracks then test
    claimed = options.declared(names)
    subject_options = SubjectOptions(scale=scale, claimed_offsets=claimed or None, max_offset=options.max_offset)
    try:
        if by_posed:
            if subject_options.scale is not None:
                # the posed videos set the background's scale: a scale pair would be overridden (or refuse the path)
                warnings.append(
                    f"{'--board' if board is not None and board.get('scale') else '--scale'}: not used: the videos the "
                    "background posed set the scale (the background's own units)"
                )
                if board is not None and board.get("scale"):
                    board.update(scale=None, scale_why="the videos the background posed set the scale")
                subject_options = replace(subject_options, scale=None)
            result, stability, aligned = largest_determined(
                lambda some: _solve_with_posed(
                    subject_tracks.of_videos(v.name for v in some),
                    some,
                    posed_tracked,
                    videos,
                    results,
                    tracks,
                    subject_options,
                ),
                inputs,
                keep=anchors,
            )
        else:
            aligned = None
            try:
                result, stability = _determined(subject_tracks, inputs, anchors, subject_options)
            except ScalePointsError as error:
                if board is None or board.get("scale") is None:
                    raise
                # the board's scale pair (not the user's) may never be triangulated together: arbitrary units
                warnings.append(f"--board: no scale from the board ({error}); the units are arbitrary")
                board.update(scale=None, scale_why=str(error))
                subject_options = replace(subject_options, scale=None)
                result, stability = _determined(subject_tracks, inputs, anchors, subject_options)
    except SubjectCalibrationError as error:
        warnings.append(f"subject path: {error}")
        return _refuse(
            unposed, results, str(error), {"used": False, "why": str(error), "anchors": anchors, "board": board}
        )
    if not stability.checked:
        warnings.append(f"subject path: poses unverified ({stability.why_unchecked})")
    for pair in result.pairs:
        if pair.claim not in (None, "held", UNTESTED):
            warnings.append(f"{options.declared_flag}: pair {pair.a}-{pair.b}: {pair.claim}")
    posed = _apply(result, stability, anchors, {v.info.name: v for v in videos}, results, warnings)
    farther = _farther_hint(inputs, set(posed) | set(anchors), options.max_offset, result.failed)
    if farther:
        warnings.append(f"subject path: {farther}")
    _warn_uncertain(stability, posed, warnings)
    guessed = [v.name for v in inputs if v.K is None and v.name in posed]
    if guessed:
        # the folds measure the poses' scatter, not this bias: on real webcams it is several times their change
        warnings.append(
            f"subject path: {', '.join(guessed)}: intrinsics self-calibrated, with the principal point held at the "
            "image centre: real lenses' principal points lie tens of pixels off it, which turns the poses by a few "
            "degrees; give --intrinsics (or --board with a calibration board's corners) for sub-degree poses"
        )
    metric = result.metric or len(anchors) >= 2 or aligned is not None  # one anchor fixes the frame, not the scale
    if not metric:
        warnings.append(
            "subject path without two background anchors or --scale: the units are arbitrary "
            "(give --scale POINT_A,POINT_B,METRES, or --board with the board's corners)"
        )
    log.info("subject path posed %s (anchors: %s)", ", ".join(posed) or "nothing", ", ".join(anchors) or "none")
    section = {**_report(result, stability, posed, anchors, metric), "board": board}
    if claimed:
        section["declared"] = _declared(result, claimed, {v.info.name: v for v in videos}, warnings, options)
    if not posed and any(v.name not in anchors for v in inputs):  # anchors alone: nothing was left to pose
        reasons = {k: v for k, v in {**result.failed, **stability.unstable}.items() if k not in anchors}
        section["why"] = (
            "it posed no video that its tracks determine ("
            + (reasons_text(reasons) or "the videos to pose have no tracks")
            + "); check that each tracked point follows the same subject in every video, and track more points or "
            "a longer, more varied motion"
        )
    # metres only when the scale came from --scale or the board; the background's units are its own
    metres = result.metric and subject_options.scale is not None and len(anchors) < 2 and aligned is None
    section["units"] = "m" if metres else None
    if aligned is not None:
        section["posed_videos"] = aligned.to_json()
    return section


def _determined(
    tracks: Tracks, inputs: list[SubjectVideo], anchors: list[str], options: SubjectOptions
) -> tuple[SubjectResult, Stability]:
    """`choose_noise` on the largest group of the videos whose tracks determine their cameras."""

    def trial(some: list[SubjectVideo]) -> tuple[SubjectResult, Stability, None]:
        return (*choose_noise(tracks.of_videos(v.name for v in some), some, options), None)

    result, stability, _ = largest_determined(trial, inputs, keep=anchors)
    return result, stability


def _solve_with_posed(
    subject_tracks: Tracks,
    inputs: list[SubjectVideo],
    posed_names: list[str],
    videos: list[VideoPlan],
    results: dict[str, dict[int, FramePose]],
    tracks: Tracks,
    options: SubjectOptions,
) -> tuple[SubjectResult, Stability, Alignment]:
    """The static videos posed in the world of the tracked videos the background posed (`solve_with_posed`),
    and the folds' check of the same solve (the posed videos kept whole, at their fitted offsets)."""
    points = subject_tracks.point_names()
    posed = [posed_video(v, results[v.info.name], tracks, points) for v in videos if v.info.name in posed_names]

    def trial(scaled: SubjectOptions) -> tuple[SubjectResult, Stability, Alignment]:
        result, aligned = solve_with_posed(subject_tracks, inputs, posed, scaled)
        # the folds: the videos the whole solve kept, at its offsets (their columns follow each fold's points)
        known = [replace(p, offset=aligned.fit(p.name).offset) for p in posed if aligned.fit(p.name).reason is None]

        def fold(part: Tracks, fold_options: SubjectOptions) -> SubjectResult:
            return solve_with_posed(part, inputs, known, fold_options)[0]

        return result, check_stability(subject_tracks, inputs, result, scaled, solve=fold, alone=False), aligned

    return choose_scale(trial, options)


def _farther_hint(inputs: list[SubjectVideo], posed: set[str], max_offset: float, failed: dict[str, str]) -> str | None:
    """For videos the subject path left unposed because no pair with them held (`failed`: their reasons): the clock
    offsets it searched (±`max_offset`) against how long the videos run, where cameras started further apart than
    that would never be found (a drone filmed for minutes). Videos refused for another reason (too few positions,
    poses that moved between folds) get no such hint: a farther search would not help them."""
    left = sorted(v.name for v in inputs if v.name not in posed and failed.get(v.name, "").startswith(UNPAIRED))
    longest = max((float(np.ptp(v.times)) for v in inputs if len(v.times) > 1), default=0.0)
    if not left or longest <= max_offset:
        return None
    return (
        f"{', '.join(left)} not posed, and two videos' clock offset is searched within ±{max_offset:g} s while the "
        f"videos run up to {longest:.0f} s: if their cameras were started further apart, register again with "
        f"--max-offset {math.ceil(longest):d}"
    )


def _refuse(
    unposed: list[VideoPlan], results: dict[str, dict[int, FramePose]], why: str, section: dict[str, Any]
) -> dict[str, Any]:
    """The static videos the background left out stay unposed, and say why; returns the report's section."""
    for video in unposed:
        results[video.info.name] = {
            f: FramePose(pose=None, reason=f"subject path: {why}") for f in results[video.info.name]
        }
    return section


def _with_board(
    tracks: Tracks,
    static: list[VideoPlan],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]],
    anchored: set[str],
    options: RegisterOptions,
    warnings: list[str],
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray | None]], tuple[str, str, float] | None, dict[str, Any]]:
    """`--board`: intrinsics from the board's views for the static videos without given ones (and not `anchored`
    by the background), and the scale from its corner spacing unless --scale was given or anchors set it. Every
    tracked video's views are fitted, so that a board file that does not match the corners gives no scale.
    Returns (intrinsics, scale, the report's `board` section)."""
    assert options.board is not None
    board = read_charuco_board(options.board)
    tracked = set(tracks.video_names())
    names = [v.info.name for v in static if v.info.name in tracked]
    if not set(tracks.point_names()) & set(board_corner_positions(board)):
        warnings.append(
            f"--board {options.board}: the tracks have no board corners (corner_<id> points): import them with "
            "`dynrecon import-tracks VIDEO... --board FILE`; the board was not used"
        )
        section = {"file": str(options.board), "used": False, "why": "no corner_<id> tracks", "scale": None}
        return intrinsics, options.scale, section
    merged = dict(intrinsics)
    found: list[BoardIntrinsics] = []
    for video in static:
        name = video.info.name
        if name not in tracked:
            continue
        fitted = calibrate_from_board(tracks, name, (video.info.width, video.info.height), board)
        found.append(fitted)
        if name in intrinsics or name in anchored:
            fitted.used = False
            fitted.why = "intrinsics given (--intrinsics)" if name in intrinsics else "posed by the background"
        elif fitted.used and fitted.K is not None:
            merged[name] = (fitted.K, fitted.dist)
            log.info("%s: intrinsics from %d board views (rms %.2f px)", name, fitted.views, fitted.rms_px or 0.0)
        else:
            warnings.append(f"{name}: intrinsics not taken from the board: {fitted.why}")
    checked = [f for f in found if f.rms_px is not None]
    misfit = [f for f in checked if not f.fits]
    scale, why = options.scale, None
    if options.scale is not None:
        why = "--scale given"
    elif len(anchored) >= 2:  # one anchor fixes the frame only
        why = "the background's anchors set the frame and scale"
    elif not checked or misfit:
        worst = max(misfit, key=lambda f: f.rms_px or 0.0) if misfit else None
        why = (
            f"the board does not fit {worst.name}'s corners ({worst.rms_px:.1f} px): wrong board file?"
            if worst is not None
            else f"no video has {MIN_VIEWS} board views to check the board file against"
        )
        warnings.append(f"--board {options.board}: no scale from the board: {why}")
    else:
        scale = board_scale(tracks, names, board)
        if scale is None:
            why = f"no two board corners are seen together in {SCALE_FRAMES} frames of two videos"
            warnings.append(f"--board: no scale from the board: {why}")
    section = {
        "file": str(options.board),
        "used": True,
        "cameras": [f.to_json() for f in found],
        "scale": None if why is not None or scale is None else [scale[0], scale[1], round(scale[2], 6)],
        "scale_why": why,
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
        # a background pose kept beside the subject path's (--subject always) would be in another world frame
        if name in results and name not in anchors:
            results[name] = {f: FramePose(pose=None, reason=f"subject path: {reason}") for f in results[name]}
            if name in result.set_aside:
                warnings.append(f"{name}: subject path: {reason}")
    return posed


def _warn_uncertain(stability: Stability, posed: list[str], warnings: list[str]) -> None:
    """Posed cameras whose folds move them by more than UNCERTAIN_DEG: kept (under the garbage limit), but said."""
    largest = stability.rotation_deg
    moved = {n: largest[n] for n in posed if largest.get(n, 0.0) > UNCERTAIN_DEG}
    if moved:
        warnings.append(
            "subject path: the folds of the tracks turn "
            + ", ".join(f"{n} by {d:.1f} deg" for n, d in moved.items())
            + ": those poses are uncertain by about as much; track more points or a longer, more varied motion"
        )


def _declared(
    result: SubjectResult,
    claimed: dict[str, float],
    by_name: dict[str, VideoPlan],
    warnings: list[str],
    options: RegisterOptions,
) -> dict[str, Any]:
    """The fitted offsets against the declared ones (`--synchronized`, `--offsets`), per camera after the pairs are
    chained and adjusted (each pair's claim is judged before: the other pairs can outvote one), in the declared
    offsets' gauge (the median difference removed); a camera more than a frame period from its claim is warned."""
    cameras = [c for c in result.cameras if c.name in claimed]
    if not cameras:
        return {"cameras": [], "agree": None}
    # Two cameras: the median would split one camera's error between both (each half off, both "agreeing"); the
    # first is the gauge, the second carries the pair's whole difference, and both are judged by it.
    pair = len(cameras) == 2
    shift = float(np.median([c.offset - claimed[c.name] for c in (cameras[:1] if pair else cameras)]))
    difference = {c.name: float(c.offset - claimed[c.name] - shift) for c in cameras}
    tolerance = {c.name: by_name[c.name].info.frame_period for c in cameras}
    judged = dict(difference)
    if pair:
        judged = dict.fromkeys(judged, difference[cameras[1].name])
        tolerance = dict.fromkeys(tolerance, max(tolerance.values()))
    agree = {name: abs(judged[name]) <= tolerance[name] for name in judged}
    rows = [
        {
            "name": c.name,
            "declared_s": round(claimed[c.name], 6),
            "fitted_s": round(float(c.offset) - shift, 6),
            "difference_s": round(difference[c.name], 6),
            "tolerance_s": round(tolerance[c.name], 6),
            "agree": agree[c.name],
        }
        for c in cameras
    ]
    if pair:
        a, b = (c.name for c in cameras)
        far = (
            []
            if agree[b]
            else [f"{b} {difference[b]:+.3f} s from {a} (two cameras: which claim is wrong cannot be told)"]
        )
    else:
        far = [f"{name} {difference[name]:+.3f} s" for name in difference if not agree[name]]
    if far:
        warnings.append(
            f"{options.declared_flag}: fitted clock offsets over a frame from the declared ones: {', '.join(far)}"
        )
    return {"cameras": rows, "agree": not far}


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
                "posed": c.name in posed,  # false: solved, then refused (its pose moved between folds)
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
                # no shared observation at any offset: no score, so no ratio
                "runner_up_ratio": round(float(p.runner_up_ratio), 3) if p.shared else None,
                "degenerate": p.degenerate,
                "reason": p.reason,
                "claim": p.claim,
            }
            for p in result.pairs
        ],
        "failed": result.failed,
        "set_aside": result.set_aside,
        "lens": result.lens.value,
        "lens_check": result.lens_check,
        "inlier_px": result.inlier_px,
        "noise_check": {f"{px:g}": trial.to_json() for px, trial in result.noise_check.items()},
        "stability": stability.to_json(),
    }
