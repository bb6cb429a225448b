"""The videos the background posed, as the subject path's frame (`sfm.subject.posed`): their per-frame poses and
intrinsics, and their tracks in the trajectory's point order."""

from __future__ import annotations

import numpy as np

from sfm.plan import FramePose, VideoPlan
from sfm.subject.observations import normalize
from sfm.subject.posed import PosedVideo, observed
from tracking.tracks import Tracks


def posed_video(video: VideoPlan, frames: dict[int, FramePose], tracks: Tracks, points: list[str]) -> PosedVideo:
    """A video the background posed frame by frame (a handheld one): its clock offset is searched."""
    F = len(video.info.times)
    R = np.full((F, 3, 3), np.nan)
    t = np.full((F, 3), np.nan)
    focal = np.full(F, np.nan)
    xy = observed(tracks, video.info.name, F, points)
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
        name=video.info.name,
        times=np.asarray(video.info.times, dtype=float),
        R=R,
        t=t,
        xy=norm,
        focal=focal,
        points=list(points),
        width=video.info.width,
        height=video.info.height,
    )
