"""`register`'s check of the background's static poses against the moving subject (`sfm.subject.agreement`).

Runs before the subject path, when the subject is tracked in two or more static videos that the background posed.
A refuted video loses its background pose (every frame says why), so that the subject path poses it like a video the
background left out; the report's `background_check` gives every pair's distances and the refuted videos.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.errors import InputError
from sfm.cameras import VideoCameras, read_cameras
from sfm.options import MAX_OFFSET_S
from sfm.plan import FramePose, VideoPlan
from sfm.subject import SubjectVideo
from sfm.subject.agreement import Agreement, check_agreement
from sfm.video import probe_video
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def _from_background(frame: FramePose) -> bool:
    """A frame posed by the background's model (not by the subject path)."""
    return frame.pose is not None and frame.source != "subject"


def _background_pose(frames: dict[int, FramePose]) -> FramePose | None:
    return next((r for r in frames.values() if _from_background(r) and r.intrinsics is not None), None)


TWO_VIEWS_WHY = (
    "the background's model holds two images, and two views of unknown focal lengths do not fix them (two-view "
    "self-calibration is unstable): give --intrinsics, or track a moving subject for the subject path"
)


def unpose_background(results: dict[str, dict[int, FramePose]], name: str, why: str) -> None:
    """Video `name` loses every pose the background gave it, each frame saying `why` (the subject path's stay)."""
    results[name] = {
        f: r if r.source == "subject" else FramePose(pose=None, reason=f"background SfM: {why}")
        for f, r in results[name].items()
    }


def refuse_two_view_focals(
    model_images: int | None, known: set[str], results: dict[str, dict[int, FramePose]]
) -> list[str]:
    """A background model of two images, some of whose videos' intrinsics are not `known` (their focal lengths
    estimated): every pose it gave is dropped (every frame says why), as the subject's refutation drops one.
    Returns the videos that lost their poses."""
    posed = [name for name, frames in results.items() if any(map(_from_background, frames.values()))]
    if model_images != 2 or set(posed) <= known:
        return []
    for name in posed:
        unpose_background(results, name, TWO_VIEWS_WHY)
    return posed


def check_background(
    videos: list[VideoPlan],
    results: dict[str, dict[int, FramePose]],
    tracks: Tracks | None,
    warnings: list[str],
    max_offset: float = MAX_OFFSET_S,
) -> dict[str, Any] | None:
    """Check the static videos the background posed against the subject's tracks; a refuted video's frames lose
    their pose (in `results`). Returns the report's `background_check` section, None where the background posed
    fewer than two static videos."""
    posed = [v for v in videos if v.static and _background_pose(results[v.info.name]) is not None]
    if len(posed) < 2:
        return None
    if tracks is None:
        why = "no 2D tracks of the subject (WS/tracks.csv or --tracks) to check the background's poses against"
        return {"checked": False, "why": why, "pairs": [], "refuted": {}}
    tracked = set(tracks.video_names())
    checked = [v for v in posed if v.info.name in tracked]
    if len(checked) < 2:
        why = "the subject is tracked in fewer than two of the static videos the background posed"
        return {"checked": False, "why": why, "pairs": [], "refuted": {}}
    inputs = []
    for video in checked:
        known = _background_pose(results[video.info.name])
        assert known is not None and known.pose is not None and known.intrinsics is not None
        inputs.append(
            SubjectVideo(
                name=video.info.name,
                width=video.info.width,
                height=video.info.height,
                times=video.info.times,
                K=known.intrinsics[0],
                dist=known.intrinsics[1],
                cam_from_world=(known.pose.rotation.matrix(), np.asarray(known.pose.translation)),
            )
        )
    agreement = _agreement(tracks, inputs, max_offset)
    for name, why in agreement.refuted.items():
        warnings.append(f"{name}: the background's pose is not used: {why}")
        unpose_background(results, name, why)
    if agreement.refuted:
        log.warning("the subject's tracks refute the background's poses of %s", ", ".join(sorted(agreement.refuted)))
        moving = sorted(v.info.name for v in videos if not v.static and _background_pose(results[v.info.name]))
        if moving and set(agreement.refuted) >= {v.name for v in inputs}:
            warnings.append(
                f"the subject's tracks refute every static pose the background gave; its poses of the moving videos "
                f"{', '.join(moving)} come from the same model: check them (register_report.json background_check)"
            )
    return {"checked": True, "why": None, **agreement.to_json()}


def background_left(videos: list[VideoPlan], results: dict[str, dict[int, FramePose]]) -> bool:
    """Whether any video still has a pose from the background (its model's points are then in the cameras' world)."""
    return any(_from_background(r) for v in videos for r in results[v.info.name].values())


def refuted_in_folder(
    folder: Path, tracks: Tracks, videos: list[Path], max_offset: float = MAX_OFFSET_S
) -> dict[str, str]:
    """The check of an earlier registration (WS/register/: cameras.json and register_report.json, made without the
    tracks) now that `tracks` exist: video -> why its background pose is refuted. Empty where the report is missing,
    the check already ran there, or fewer than two tracked static videos were posed by the background."""
    try:
        report = json.loads((folder / "register_report.json").read_text(encoding="utf-8"))
        cameras = read_cameras(folder / "cameras.json")
    except (OSError, ValueError, InputError):
        return {}
    if (report.get("background_check") or {}).get("checked"):
        return {}
    static = {
        v["name"]
        for v in report.get("videos", [])
        if v.get("camera") == "static" and v.get("posed_by", "none") not in ("none", "subject")
    }
    paths = {p.stem: p for p in videos}
    inputs = []
    for video in cameras.videos:
        if video.name not in static or video.name not in paths or not video.frames:
            continue
        first = video.frames[0]
        try:
            own = static_times(video, paths[video.name])
        except InputError as error:
            log.warning("%s: not checked against the tracks: %s", video.name, error)
            continue
        inputs.append(
            SubjectVideo(
                name=video.name,
                width=video.width,
                height=video.height,
                times=own,
                K=first.K,
                dist=first.dist,
                cam_from_world=(first.R, first.t),
            )
        )
    tracked = set(tracks.video_names())
    inputs = [v for v in inputs if v.name in tracked]
    if len(inputs) < 2:
        return {}
    agreement = _agreement(tracks, inputs, max_offset)
    if not agreement.refuted:
        checked = [p for p in agreement.pairs if p.checked]
        log.info(
            "the background's static poses agree with the subject's tracks (%d of %d pairs checked)",
            len(checked),
            len(agreement.pairs),
        )
    return agreement.refuted


def static_times(video: VideoCameras, path: Path | None) -> np.ndarray:
    """(F,) own seconds of every frame of a static video: from cameras.json when it has every frame's time (a static
    video's every frame is posed), else probed from its file."""
    times = np.array([f.time if f.time is not None else np.nan for f in video.frames], dtype=float)
    if [f.frame for f in video.frames] == list(range(len(video.frames))) and np.isfinite(times).all():
        return times
    if path is None:
        raise InputError(None, f"{video.name}: cameras.json lacks frame times and its video was not given")
    return probe_video(path).times


def _agreement(tracks: Tracks, videos: list[SubjectVideo], max_offset: float = MAX_OFFSET_S) -> Agreement:
    """`check_agreement` of `videos` on their own rows of `tracks`."""
    names = {v.name for v in videos}
    rows = tracks.of_videos(names)
    return check_agreement(rows, videos, max_offset)
