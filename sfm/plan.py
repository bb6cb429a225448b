"""What `register` decided per video (which frames go to SfM, which need a pose) and what it got per frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from sfm.frames import Resize, sfm_folder
from sfm.keyframes import KeyframeChoice
from sfm.static import MotionTest
from sfm.video import ProbedVideo

BACKGROUND_IMAGE = "background"  # a static video's one SfM image: frames/<video>/background.jpg


@dataclass(kw_only=True)
class VideoPlan:
    info: ProbedVideo
    resize: Resize
    sfm_frames: np.ndarray  # (S,) decoded frame numbers sent to SfM (empty for a static video)
    wanted: np.ndarray  # (W,) every frame that should get a pose (includes sfm_frames)
    motion: MotionTest | None = None  # the measured static/moving decision (also when the user chose)
    motion_given: bool = False  # `static` set by --camera-motion, not by the measurement
    static: bool = False  # one camera pose for every frame, from one background image
    keyframes: KeyframeChoice | None = None  # how sfm_frames were chosen (None for a static video)

    @property
    def background_name(self) -> str:
        """The SfM image name of a static video's background (relative to the frames folder)."""
        return f"{sfm_folder(self.info.name)}/{BACKGROUND_IMAGE}.jpg"


@dataclass(kw_only=True)
class FramePose:
    """The outcome for one wanted frame. `source`: "sfm", "tracked" (PnP of the keyframes' tracked features),
    "pnp" (PnP of its SIFT features), "pnp (dropped by SfM)", "static" or "subject"; None without pose."""

    pose: pycolmap.Rigid3d | None
    reason: str | None = None  # why there is no pose
    source: str | None = None
    error: float | None = None  # mean reprojection error, original pixels
    intrinsics: tuple[np.ndarray, np.ndarray | None] | None = None  # (K, dist), OpenCV, original pixels
    inliers: int | None = None  # PnP inliers (the model's observations for an SfM frame)
