"""The solver's input from the contract files (cameras.json + tracks.csv), validating the links between them.

The bridge between the stage files and `reconstruct.solver`, which reads no file format itself.
"""

from __future__ import annotations

import logging

import numpy as np

from dynrecon.errors import InputError, NotEnoughDataError
from reconstruct.solver.problem import Problem
from sfm.cameras import CameraSet
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def build_problem(cameras: CameraSet, tracks: Tracks, point_names: list[str] | None = None) -> Problem:
    """Join poses and observations. Unknown videos are errors; observations of unposed frames are dropped with a
    warning (registration may fail on some frames, and a pose is never invented)."""
    videos = [v for v in cameras.videos if v.frames]
    if len(videos) < 2:
        raise NotEnoughDataError(
            f"{len(videos)} video(s) with posed frames in the cameras file: the solver needs at least 2 "
            "(register more videos, or check that their frames got poses)"
        )
    video_names = [v.name for v in videos]
    frame_lists = [sorted(v.frames, key=lambda f: f.frame) for v in videos]
    index: dict[tuple[str, int], int] = {}
    for video, frames in zip(videos, frame_lists, strict=True):
        for frame in frames:
            index[(video.name, frame.frame)] = len(index)
    all_frames = [f for frames in frame_lists for f in frames]
    F = len(all_frames)

    names = point_names if point_names is not None else tracks.point_names()
    point_index = {name: i for i, name in enumerate(names)}
    uv = np.full((F, len(names), 2), np.nan)
    known_videos = set(video_names) | {v.name for v in cameras.videos}
    unposed: list[int] = []
    for row in range(len(tracks)):
        video_name = tracks.video[row]
        if video_name not in known_videos:
            raise InputError(
                tracks.path,
                f"video {video_name!r} is not in the cameras file",
                where=tracks.where(row),
                fix=f"known videos: {', '.join(sorted(known_videos))}; rename or register it",
            )
        fi = index.get((video_name, int(tracks.frame[row])))
        if fi is None:
            unposed.append(row)
            continue
        pi = point_index.get(tracks.point[row])
        if pi is None:
            continue
        uv[fi, pi] = tracks.xy[row]
    if unposed:
        log.warning(
            "%s: %d observation(s) on frames without a pose were ignored (first: %s, video %r frame %d)",
            tracks.path or "tracks",
            len(unposed),
            tracks.where(unposed[0]),
            tracks.video[unposed[0]],
            int(tracks.frame[unposed[0]]),
        )
    if not np.any(~np.isnan(uv[..., 0])):
        raise NotEnoughDataError(
            f"{tracks.path or 'tracks'}: no observation falls on a posed frame "
            "(check video names and frame numbers against the cameras file)"
        )
    return Problem(
        video_names=video_names,
        video_index=np.array([vi for vi, frames in enumerate(frame_lists) for _ in frames], dtype=np.int64),
        frames=np.array([f.frame for f in all_frames], dtype=np.int64),
        times=np.array([np.nan if f.time is None else f.time for f in all_frames]),
        point_names=list(names),
        K=np.stack([f.K for f in all_frames]),
        R=np.stack([f.R for f in all_frames]),
        t=np.stack([f.t for f in all_frames]),
        dist=[f.dist for f in all_frames],
        uv=uv,
    )
