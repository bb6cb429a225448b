"""The solver's input from the contract files (cameras.json + tracks.csv), validating the links between them.

The bridge between the stage files and `reconstruct.solver`, which reads no file format itself.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynrecon.errors import InputError, NotEnoughDataError
from reconstruct.screen import remove_spikes
from reconstruct.solver.problem import Problem
from sfm.cameras import CameraSet
from tracking.tracks import IMAGE_MARGIN, Tracks, inside_image

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class RejectedObservations:
    """Rows of tracks.csv that `build_problem` set aside: outside their video's image (beyond IMAGE_MARGIN of its
    size) or not finite (`count`; `first` names the first such row, file and line), and observations far off
    their own track (`spikes`, reconstruct/screen.py)."""

    count: int = 0
    first: str | None = None
    spikes: int = 0
    unposed: int = 0  # rows on frames that registration did not pose: ignored, a pose is never invented

    def to_json(self) -> dict[str, Any]:
        return {
            "outside_image": self.count,
            "first": self.first,
            "margin": IMAGE_MARGIN,
            "isolated_spikes": self.spikes,
            "on_unposed_frames": self.unposed,
        }


def build_problem(cameras: CameraSet, tracks: Tracks, point_names: list[str] | None = None) -> Problem:
    """Join poses and observations (see `build_problem_checked`, which also returns the rejected rows)."""
    return build_problem_checked(cameras, tracks, point_names)[0]


def build_problem_checked(
    cameras: CameraSet, tracks: Tracks, point_names: list[str] | None = None
) -> tuple[Problem, RejectedObservations]:
    """Join poses and observations. Unknown videos are errors; observations of unposed frames are dropped with a
    warning (registration may fail on some frames, and a pose is never invented); observations outside their
    video's image (with IMAGE_MARGIN) or not finite are rejected, counted and warned about once, and so are
    isolated spikes off their own track (reconstruct/screen.py)."""
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
    inside = _inside_images(cameras, tracks)
    unposed: list[int] = []
    rejected: list[int] = []
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
        if not inside[row]:
            rejected.append(row)
            continue
        pi = point_index.get(tracks.point[row])
        if pi is None:
            continue
        uv[fi, pi] = tracks.xy[row]
    _warn_unposed(tracks, unposed)
    rejection = _rejection(cameras, tracks, rejected)
    rejection.unposed = len(unposed)
    if not np.any(~np.isnan(uv[..., 0])):
        raise NotEnoughDataError(
            f"{tracks.path or 'tracks'}: no observation falls on a posed frame "
            "(check video names and frame numbers against the cameras file)"
        )
    problem = Problem(
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
    problem, rejection.spikes = remove_spikes(problem)
    return problem, rejection


def _warn_unposed(tracks: Tracks, unposed: list[int]) -> None:
    if unposed:
        log.warning(
            "%s: %d observation(s) on frames without a pose were ignored (first: %s, video %r frame %d)",
            tracks.path or "tracks",
            len(unposed),
            tracks.where(unposed[0]),
            tracks.video[unposed[0]],
            int(tracks.frame[unposed[0]]),
        )


def _rejection(cameras: CameraSet, tracks: Tracks, rejected: list[int]) -> RejectedObservations:
    """The count of rejected rows, with one warning naming the first."""
    rejection = RejectedObservations(count=len(rejected))
    if rejected:
        row = rejected[0]
        video = cameras.video(tracks.video[row])
        rejection.first = f"{tracks.path or 'tracks'}:{tracks.where(row)}"
        log.warning(
            "%s: %d observation(s) outside the image (beyond %d %% of its size) or not finite were rejected "
            "(first: %s, video %r frame %d at x, y = %.6g, %.6g in a %dx%d image)",
            tracks.path or "tracks",
            len(rejected),
            round(100 * IMAGE_MARGIN),
            tracks.where(row),
            video.name,
            int(tracks.frame[row]),
            tracks.xy[row, 0],
            tracks.xy[row, 1],
            video.width,
            video.height,
        )
    return rejection


def _inside_images(cameras: CameraSet, tracks: Tracks) -> np.ndarray:
    """(N,) bool: which rows of `tracks` are finite and inside their video's image (unknown videos: True)."""
    sizes = {v.name: (v.width, v.height) for v in cameras.videos}
    wh = np.array([sizes.get(name, (np.inf, np.inf)) for name in tracks.video], dtype=float).reshape(-1, 2)
    return inside_image(tracks.xy, wh[:, 0], wh[:, 1])
