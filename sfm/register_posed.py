"""The videos the background posed, as the subject path's frame (`sfm.subject.posed`): their per-frame poses and
intrinsics, and their tracks in the trajectory's point order."""

from __future__ import annotations

import numpy as np

from sfm.plan import FramePose, VideoPlan
from sfm.subject import SubjectResult, SubjectVideo
from sfm.subject.observations import normalize
from sfm.subject.posed import PosedVideo
from tracking.tracks import Tracks


def posed_video(video: VideoPlan, frames: dict[int, FramePose], tracks: Tracks, points: list[str]) -> PosedVideo:
    """A video the background posed frame by frame (a handheld one): its clock offset is searched."""
    F = len(video.info.times)
    R = np.full((F, 3, 3), np.nan)
    t = np.full((F, 3), np.nan)
    focal = np.full(F, np.nan)
    xy = _pixels(video.info.name, F, tracks, points)
    norm = np.full_like(xy, np.nan)
    groups: dict[bytes, list[int]] = {}
    lenses: dict[bytes, tuple[np.ndarray, np.ndarray | None]] = {}
    for f, result in frames.items():
        if result.pose is None or result.intrinsics is None or not 0 <= f < F:
            continue
        R[f] = result.pose.rotation.matrix()
        t[f] = np.asarray(result.pose.translation)
        K, dist = result.intrinsics
        key = np.asarray(K, dtype=float).tobytes() + (b"" if dist is None else np.asarray(dist, dtype=float).tobytes())
        groups.setdefault(key, []).append(f)
        lenses[key] = (np.asarray(K, dtype=float), dist)
    for key, members in groups.items():  # one undistortion per lens (most videos have one)
        K, dist = lenses[key]
        norm[members] = normalize(xy[members], K, dist)
        focal[members] = 0.5 * (K[0, 0] + K[1, 1])
    return PosedVideo(
        name=video.info.name, times=np.asarray(video.info.times, dtype=float), R=R, t=t, xy=norm, focal=focal
    )


def static_anchor(
    video: SubjectVideo, frames: dict[int, FramePose], tracks: Tracks, result: SubjectResult
) -> PosedVideo:
    """A static video the background posed, which the subject path solved too: its pose on every frame, its
    offset the subject path's (searched when the subject path did not pose it)."""
    pose = next(r for r in frames.values() if r.pose is not None)
    F = len(video.times)
    K = np.asarray(video.K if video.K is not None else pose.intrinsics[0], dtype=float)  # type: ignore[index]
    dist = video.dist if video.K is not None else (pose.intrinsics[1] if pose.intrinsics else None)
    points = list(result.points)
    camera = result.camera(video.name)
    return PosedVideo(
        name=video.name,
        times=np.asarray(video.times, dtype=float),
        R=np.broadcast_to(pose.pose.rotation.matrix(), (F, 3, 3)).copy(),  # type: ignore[union-attr]
        t=np.broadcast_to(np.asarray(pose.pose.translation), (F, 3)).copy(),  # type: ignore[union-attr]
        xy=normalize(_pixels(video.name, F, tracks, points), K, dist),
        focal=np.full(F, 0.5 * (K[0, 0] + K[1, 1])),
        offset=None if camera is None else camera.offset,
    )


def _pixels(name: str, n_frames: int, tracks: Tracks, points: list[str]) -> np.ndarray:
    """(F, P, 2) pixels of one video's tracks, points in `points`' order (others dropped), NaN = unseen."""
    xy = np.full((n_frames, len(points), 2), np.nan)
    index = {p: i for i, p in enumerate(points)}
    for video, frame, point, uv in zip(tracks.video, tracks.frame, tracks.point, tracks.xy, strict=True):
        if video == name and point in index and 0 <= frame < n_frames:
            xy[frame, index[point]] = uv
    return xy
