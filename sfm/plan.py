"""What `register` decided per video (which frames go to SfM, which need a pose) and what it got per frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from sfm.frames import Resize
from sfm.video import VideoInfo


@dataclass(kw_only=True)
class VideoPlan:
    info: VideoInfo
    resize: Resize
    sfm_frames: np.ndarray  # (S,) decoded frame numbers sent to SfM
    wanted: np.ndarray  # (W,) every frame that should get a pose (includes sfm_frames)


@dataclass(kw_only=True)
class FramePose:
    """The outcome for one wanted frame. `source`: "sfm", "pnp" or "pnp (dropped by SfM)"; None without pose."""

    pose: pycolmap.Rigid3d | None
    reason: str | None = None  # why there is no pose
    source: str | None = None
    error: float | None = None  # mean reprojection error, original pixels
    intrinsics: tuple[np.ndarray, np.ndarray | None] | None = None  # (K, dist), OpenCV, original pixels
    inliers: int | None = None  # PnP inliers
