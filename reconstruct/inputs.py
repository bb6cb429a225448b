"""The solver's input from the contract files (cameras.json + tracks.csv), validating the links between them.

The bridge between the stage files and `reconstruct.solver`, which reads no file format itself.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.errors import InputError, NotEnoughDataError
from reconstruct.facing import check_facing
from reconstruct.screen import remove_spikes
from reconstruct.solver.problem import Problem, reconstructable_points
from reconstruct.solver.unseen_frames import take_frames
from sfm.cameras import CameraSet, FrameCamera, VideoCameras
from tracking.tracks import IMAGE_MARGIN, Tracks, inside_image

log = logging.getLogger(__name__)

MIN_LINK = 3  # observations of a point in each of two videos that link them (a stray detection does not)
BASELINE_TOLERANCE = 1e-9  # camera centres closer than this (relative to their magnitude) are one point


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
    cameras: CameraSet, tracks: Tracks, point_names: list[str] | None = None, *, cameras_path: Path | None = None
) -> tuple[Problem, RejectedObservations]:
    """Join poses and observations. Unknown videos are errors; observations of unposed frames are dropped with a
    warning (registration may fail on some frames, and a pose is never invented); observations outside their
    video's image (with IMAGE_MARGIN) or not finite are rejected, counted and warned about once, and so are
    isolated spikes off their own track (reconstruct/screen.py). `cameras_path` names the cameras file in errors."""
    videos = [v for v in cameras.videos if v.frames]
    source = cameras_path or "the cameras file"
    if len(videos) < 2:
        raise NotEnoughDataError(
            f"{source}: {len(videos)} video(s) with posed frames: the solver needs at least 2 "
            "(register more videos, or check that their frames got poses)"
        )
    _check_baseline(videos, source)
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
    if not known_videos.issuperset(tracks.video):
        unknown = next(row for row, name in enumerate(tracks.video) if name not in known_videos)
        raise InputError(
            tracks.path,
            f"video {tracks.video[unknown]!r} is not in the cameras file",
            where=tracks.where(unknown),
            fix=f"known videos: {', '.join(sorted(known_videos))}; rename or register it",
        )
    inside = _inside_images(cameras, tracks)
    rows = _frame_rows(video_names, frame_lists, tracks)
    if rows is None:  # duplicate names or frames in memory, or frames not integers: the plain loop
        unposed, rejected = _fill_by_row(uv, index, point_index, inside, tracks)
    else:
        unposed, rejected = _fill(uv, rows, point_index, inside, tracks)
    _warn_unposed(tracks, unposed)
    rejection = _rejection(cameras, tracks, rejected)
    rejection.unposed = len(unposed)
    if not len(tracks.video):
        raise NotEnoughDataError(f"{tracks.path or 'tracks'}: no observations, only a header (track or import some)")
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
    problem = _without_unseen_videos(problem, tracks.path)
    offsets = {video.name: video.clock_offset for video in cameras.videos}
    problem = _linked(problem, tracks.path, all(offsets.get(name) is not None for name in problem.video_names))
    if not reconstructable_points(problem).any():  # here, where the tracks file can be named
        raise NotEnoughDataError(
            f"{tracks.path or 'tracks'}: none of the {problem.num_points} point(s) is seen in two different videos: "
            "nothing can be reconstructed (each point needs observations from at least two videos; check that the "
            "point names are the same in every video)"
        )
    check_facing(problem, source)
    return problem, rejection


def _without_unseen_videos(problem: Problem, tracks_path: Path | None) -> Problem:
    """The problem without the videos that observe nothing: their frames carry no data and their clocks link to
    nothing, so they would only fail the clock model of the videos that do observe the points."""
    seen = np.array([problem.observed[problem.video_index == v].any() for v in range(len(problem.video_names))])
    if seen.all() or not seen.any():
        return problem
    unseen = [name for name, ok in zip(problem.video_names, seen, strict=True) if not ok]
    log.warning(
        "%s: no observation of video(s) %s on a posed frame: left out of the solve (no rows in points3d.csv)",
        tracks_path or "tracks",
        ", ".join(unseen),
    )
    return take_frames(problem, seen[problem.video_index])


def video_groups(problem: Problem, min_link: int = MIN_LINK) -> list[list[int]]:
    """The videos in groups linked by shared points (a point each of two videos observes `min_link` times or more,
    or in half its frames when it has fewer, links them: a stray detection or two does not), largest first."""
    N = len(problem.video_names)
    rows = [problem.video_index == v for v in range(N)]
    need = [min(min_link, max(1, int(np.ceil(0.5 * own.sum())))) for own in rows]
    seen = np.stack([problem.observed[own].sum(axis=0) >= n for own, n in zip(rows, need, strict=True)])  # (N, P)
    parent = list(range(N))

    def root(v: int) -> int:
        while parent[v] != v:
            v = parent[v]
        return v

    for p in range(problem.num_points):
        videos = np.flatnonzero(seen[:, p]).tolist()
        for v in videos[1:]:
            parent[root(v)] = root(videos[0])
    groups: dict[int, list[int]] = {}
    for v in range(N):
        groups.setdefault(root(v), []).append(v)
    return sorted(groups.values(), key=lambda group: (-len(group), group[0]))


def _linked(problem: Problem, tracks_path: Path | None, clocks_given: bool) -> Problem:
    """The problem on videos the tracks link. Unless cameras.json gives every video's clock offset (which alone ties
    the videos: each group's points are then placed by its own videos, reconstruct/registered_offsets.py), a video
    that shares no point with the others is left out (its clock links to nothing, as an unseen video's), and videos
    in two or more groups that share no point are refused: the joint solve placed one group's points anywhere along
    their rays (at a camera's centre, measured)."""
    groups = video_groups(problem)
    linked = [group for group in groups if len(group) > 1]
    if not linked:  # nothing links any two videos: the later checks say what is missing
        return problem
    described = [_described(problem, group) for group in linked]
    if clocks_given:
        if len(linked) > 1:
            log.warning(
                "the videos form %d groups that share no tracked point: %s; the cameras file gives every clock "
                "offset, which alone ties them (each group's points are placed by its own videos)",
                len(linked),
                "; ".join(described),
            )
        return problem
    if len(linked) > 1:
        first = ",".join(problem.video_names[v] for v in linked[0])
        raise InputError(
            tracks_path,
            f"the videos form {len(linked)} groups that share no tracked point: " + "; ".join(described),
            fix=f"no point links their clocks or depths: solve each group on its own (`dynrecon solve --videos "
            f"{first}` and so on), or track a point that both groups see",
        )
    lone = [v for group in groups if len(group) == 1 for v in group]
    if not lone:
        return problem
    log.warning(
        "%s: video(s) %s share no tracked point (%d observations or more) with the others: left out of the solve "
        "(nothing links their clocks; no rows in points3d.csv)",
        tracks_path or "tracks",
        ", ".join(problem.video_names[v] for v in lone),
        MIN_LINK,
    )
    return take_frames(problem, ~np.isin(problem.video_index, lone))


def _described(problem: Problem, group: list[int]) -> str:
    """'cam0, cam1 (points a, b, c and 4 more)': a group's videos and the points they see."""
    seen = np.asarray(problem.observed[np.isin(problem.video_index, group)].any(axis=0))
    names = [name for name, ok in zip(problem.point_names, seen.tolist(), strict=True) if ok]
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return f"{', '.join(problem.video_names[v] for v in group)} (points {shown})"


def _check_baseline(videos: list[VideoCameras], source: Path | str) -> None:
    """Refuse cameras that all sit at one point: rays from one centre meet nowhere (one pose copied to every video
    is the usual cause); warn about two static videos at one pose, whose rays of a point never cross."""
    centers = [np.array([frame.center for frame in video.frames]) for video in videos]
    every = np.concatenate(centers)
    scale = max(1.0, float(np.abs(every).max()))
    if float(np.ptp(every, axis=0).max()) <= BASELINE_TOLERANCE * scale:
        raise NotEnoughDataError(
            f"{source}: every posed frame of the {len(videos)} videos has its camera at the same point "
            f"{np.round(every[0], 6).tolist()}: no baseline to triangulate from (each camera needs its own pose; "
            "was one pose copied to every video?)"
        )
    fixed = [
        (video.name, c[0])
        for video, c in zip(videos, centers, strict=True)
        if np.ptp(c, axis=0).max() <= BASELINE_TOLERANCE * scale
    ]
    for i, (name, center) in enumerate(fixed):
        for other, center_other in fixed[i + 1 :]:
            if np.abs(center - center_other).max() <= BASELINE_TOLERANCE * scale:
                log.warning(
                    "videos %r and %r have their camera at the same point: their rays of a point never cross, so "
                    "they place nothing in depth together (one camera's pose given twice?)",
                    name,
                    other,
                )


def _frame_rows(video_names: list[str], frame_lists: list[list[FrameCamera]], tracks: Tracks) -> np.ndarray | None:
    """(N,) each row's frame index in the problem (frames in video then frame order), -1 where its frame has no
    pose; None when names or frames repeat, or `tracks.frame` does not hold integers (the row loop then decides)."""
    frame = np.asarray(tracks.frame)
    if len(set(video_names)) != len(video_names) or not np.issubdtype(frame.dtype, np.signedinteger):
        return None
    numbers = [np.array([f.frame for f in frames]) for frames in frame_lists]
    if any(not np.issubdtype(n.dtype, np.signedinteger) or np.any(np.diff(n) <= 0) for n in numbers):
        return None
    numbers = [n.astype(np.int64) for n in numbers]
    frame = frame.astype(np.int64)
    codes, names = _codes(tracks.video)
    out = np.full(len(tracks), -1, dtype=np.int64)
    offsets = np.cumsum([0, *(len(n) for n in numbers)])
    where = {name: i for i, name in enumerate(video_names)}
    for code, name in enumerate(names):
        if name not in where:
            continue
        v = where[name]
        rows = np.flatnonzero(codes == code)
        at = np.minimum(np.searchsorted(numbers[v], frame[rows]), len(numbers[v]) - 1)
        hit = numbers[v][at] == frame[rows]
        out[rows[hit]] = offsets[v] + at[hit]
    return out


def _fill(
    uv: np.ndarray, frame_rows: np.ndarray, point_index: dict[str, int], inside: np.ndarray, tracks: Tracks
) -> tuple[list[int], list[int]]:
    """Copy the rows' positions into uv (F, P, 2) at their frame and point; the rows on unposed frames and the rows
    outside their image, each in row order. A row of an unknown point is skipped."""
    posed = frame_rows >= 0
    codes, names = _codes(tracks.point)
    point_rows = np.array([point_index.get(name, -1) for name in names], dtype=np.int64)[codes]
    use = posed & inside & (point_rows >= 0)
    fi, pi = frame_rows[use], point_rows[use]
    if len(np.unique(fi * uv.shape[1] + pi)) < len(fi):  # a (frame, point) twice in memory: the last row wins
        for row in np.flatnonzero(use).tolist():
            uv[frame_rows[row], point_rows[row]] = tracks.xy[row]
    else:
        uv[fi, pi] = np.asarray(tracks.xy)[use]
    return np.flatnonzero(~posed).tolist(), np.flatnonzero(posed & ~inside).tolist()


def _fill_by_row(
    uv: np.ndarray, index: dict[tuple[str, int], int], point_index: dict[str, int], inside: np.ndarray, tracks: Tracks
) -> tuple[list[int], list[int]]:
    """`_fill`, one row at a time, with the frame index `index` of (video, frame)."""
    unposed: list[int] = []
    rejected: list[int] = []
    for row in range(len(tracks)):
        fi = index.get((tracks.video[row], int(tracks.frame[row])))
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
    return unposed, rejected


def _codes(names: list[str]) -> tuple[np.ndarray, list[str]]:
    """(N,) int64 index of each name among the distinct names, and those names in order of first appearance."""
    index = {name: i for i, name in enumerate(dict.fromkeys(names))}
    return np.fromiter(map(index.__getitem__, names), dtype=np.int64, count=len(names)), list(index)


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
    codes, names = _codes(tracks.video)
    wh = np.array([sizes.get(name, (np.inf, np.inf)) for name in names], dtype=float).reshape(-1, 2)[codes]
    return inside_image(tracks.xy, wh[:, 0], wh[:, 1])
