"""Is a video's camera static? And if so, its one background image for SfM.

A camera on a tripod sees the same background in every frame: sending its frames to SfM as separate images only
adds zero-baseline pairs, which split models and cost most of the matching time. One background image per static
video (the temporal median of sampled frames, in which a moving subject disappears) is matched across videos
instead, and every frame of the video takes that image's pose.

The test: background corners of the median image are tracked (pyramidal LK, forward-backward check) into each
sampled frame. A static camera leaves them where they are; a handheld one moves them all. Pixels where the frames
differ from the median most of the time (the moving subject) and the tracked subject points are masked out first.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from sfm.frames import Resize
from sfm.video import ProbedVideo, read_frames

log = logging.getLogger(__name__)

WORK_LONG_SIDE = 640  # motion is measured on frames of this long side (pixels)
MIN_CORNERS = 20  # fewer trackable background corners: the test cannot decide, the video counts as moving
SAMPLES = 24  # frames sampled evenly along the video for the test and the median image
MAX_SHIFT = 0.006  # static when no sampled frame moves the background by more (fraction of long side)
MIN_TRACKED = 0.2  # share of background corners that must survive the forward-backward check
SETTLED = 0.0012  # samples within this shift (fraction of long side) sit at the camera's main position
MIN_ODD = 2  # sampled frames off the background (shifted or lost) that make a camera moving
MOVED = 0.002  # a static camera whose samples sit this far from it for MOVED_RUN samples in a row was bumped
MOVED_RUN = 3  # (one sample off is a passing occlusion, not a move)


@dataclass(kw_only=True)
class MotionTest:
    """The measured decision for one video; `shifts`: median corner displacement per sampled frame (pixels of the
    original video)."""

    static: bool
    reason: str
    frames: list[int] = field(default_factory=list)
    shifts: list[float] = field(default_factory=list)
    tracked: list[float] = field(default_factory=list)  # share of corners tracked per sampled frame
    corners: int = 0
    settled: list[int] = field(default_factory=list)  # sampled frames at the camera's main position
    moved: str | None = None  # a static camera that was bumped or refocused: where and by how much

    def to_json(self) -> dict[str, Any]:
        return {
            "static": self.static,
            "reason": self.reason,
            "corners": self.corners,
            "max_shift_px": round(max(self.shifts), 3) if self.shifts else None,
            "median_shift_px": round(float(np.median(self.shifts)), 3) if self.shifts else None,
            "min_tracked": round(min(self.tracked), 3) if self.tracked else None,
            "frames_sampled": len(self.frames),
            "moved": self.moved,
        }


def sample_frames(info: ProbedVideo, count: int) -> np.ndarray:
    """Up to `count` frame numbers spread evenly over the video, first and last included."""
    return np.unique(np.round(np.linspace(0, info.num_frames - 1, min(count, info.num_frames))).astype(np.int64))


def _gray(image: np.ndarray, resize: Resize) -> np.ndarray:
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    if resize.scale != 1.0:
        gray = cv2.resize(gray, (resize.width, resize.height), interpolation=cv2.INTER_AREA)
    return gray


def _camera_shift(before: np.ndarray, after: np.ndarray, shape: tuple[int, ...]) -> float:
    """How far the camera moved the background: the largest displacement, over the image corners, of the similarity
    that RANSAC fits to the tracked corners (the largest rigidly moving group; a subject moves otherwise)."""
    if len(before) < 6:
        return float("inf")
    model, inliers = cv2.estimateAffinePartial2D(
        before, after, method=cv2.RANSAC, ransacReprojThreshold=1.0, maxIters=500, confidence=0.995
    )
    if model is None or inliers is None or inliers.sum() < 6:
        return float("inf")
    h, w = shape[:2]
    frame = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=float)
    mapped = frame @ model[:, :2].T + model[:, 2]
    return float(np.linalg.norm(mapped - frame, axis=1).max())


def _moving_pixels(stack: np.ndarray, median: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that differ from the median in most sampled frames (a subject that came and went)."""
    differs = np.abs(stack.astype(np.int16) - median.astype(np.int16)) > 25
    return differs.mean(axis=0) > 0.3


def measure_motion(info: ProbedVideo, subject_mask: np.ndarray | None = None) -> MotionTest:
    """Measure whether the camera of `info` moves (the sampled frame numbers are in the test's `frames`).

    subject_mask: (H, W) uint8 at WORK_LONG_SIDE, 0 where the tracked subject is (optional)."""
    frames = sample_frames(info, SAMPLES)
    work = Resize.for_video(info, WORK_LONG_SIDE)
    grays = np.stack([_gray(image, work) for _, image in read_frames(info.path, frames)])
    if len(frames) < 2:
        return MotionTest(static=False, reason="fewer than 2 frames: treated as moving", frames=frames.tolist())
    median = np.median(grays, axis=0).astype(np.uint8)
    mask = np.where(_moving_pixels(grays, median), 0, 255).astype(np.uint8)
    if subject_mask is not None:
        mask = np.minimum(mask, subject_mask)
    corners = cv2.goodFeaturesToTrack(median, maxCorners=400, qualityLevel=0.01, minDistance=8, mask=mask)
    if corners is None or len(corners) < MIN_CORNERS:
        # Everything moves (a handheld camera) or the view has no texture: no static background to lean on.
        corners = cv2.goodFeaturesToTrack(median, maxCorners=400, qualityLevel=0.01, minDistance=8)
    count = 0 if corners is None else len(corners)
    if corners is None or count < MIN_CORNERS:
        return MotionTest(
            static=False,
            reason=f"only {count} trackable corners: treated as moving",
            corners=count,
            frames=frames.tolist(),
        )
    lk: dict[str, Any] = {
        "winSize": (21, 21),
        "maxLevel": 4,
        "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    }
    to_original = 1.0 / work.scale
    shifts, tracked = [], []
    for gray in grays:
        moved, status, _ = cv2.calcOpticalFlowPyrLK(median, gray, corners, None, **lk)  # type: ignore[call-overload]
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(gray, median, moved, None, **lk)  # type: ignore[call-overload]
        good = (status.ravel() == 1) & (status_back.ravel() == 1)
        good &= np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < 1.0
        tracked.append(float(good.mean()))
        shifts.append(_camera_shift(corners.reshape(-1, 2)[good], moved.reshape(-1, 2)[good], gray.shape) * to_original)
    limit = MAX_SHIFT * max(info.width, info.height)
    # one odd sample (a damaged or smeared frame, a flash, a knock) does not make a camera move: a moving one
    # is off in many samples
    lost = np.array(tracked) < MIN_TRACKED
    off = np.array(shifts) > limit
    worst = int(np.argmax(shifts))
    if lost.sum() >= MIN_ODD:
        at = int(np.argmin(tracked))
        static = False
        reason = f"moving: only {tracked[at]:.0%} of {count} background corners tracked into frame {int(frames[at])}"
    elif (off | lost).sum() >= MIN_ODD:
        static = False
        reason = f"moving: background shifted {shifts[worst]:.1f} px at frame {int(frames[worst])} (> {limit:.1f} px)"
    else:
        static = True
        steady = [shift for shift, odd in zip(shifts, off | lost, strict=True) if not odd]
        reason = (
            f"static: background shifts at most {max(steady, default=0.0):.2f} px over {len(frames)} sampled frames"
        )
        if (off | lost).any():
            at = int(np.flatnonzero(off | lost)[0])
            reason += (
                f" (one odd sample ignored: frame {int(frames[at])}, {shifts[at]:.1f} px, {tracked[at]:.0%} of the "
                "corners tracked)"
            )
    long_side = max(info.width, info.height)
    settled = [int(f) for f, shift in zip(frames, shifts, strict=True) if shift <= SETTLED * long_side]
    return MotionTest(
        static=static,
        reason=reason,
        frames=frames.tolist(),
        shifts=shifts,
        tracked=tracked,
        corners=count,
        settled=settled,
        moved=_moved(info.name, frames, shifts, MOVED * long_side) if static else None,
    )


def _moved(name: str, frames: np.ndarray, shifts: list[float], limit: float) -> str | None:
    """One line when a static camera sat away from its main position for MOVED_RUN or more samples in a row."""
    away = np.array(shifts) > limit
    runs = np.flatnonzero(np.diff(np.concatenate([[0], away.astype(np.int8), [0]])))  # starts and ends of runs
    for start, end in zip(runs[::2], runs[1::2], strict=True):
        if end - start >= MOVED_RUN:
            return (
                f"{name}: the camera moved: frames {int(frames[start])}-{int(frames[end - 1])} sit "
                f"{float(np.median(shifts[start:end])):.1f} px from its main position (bumped or refocused); "
                "they take the main position's pose"
            )
    return None


def background_image(info: ProbedVideo, frames: np.ndarray, resize: Resize) -> np.ndarray:
    """The temporal median (BGR, SfM pixels) of `frames` (a static camera's settled ones: a median over two
    positions blurs): a subject that moves through the view disappears."""
    images = [
        cv2.resize(image, (resize.width, resize.height), interpolation=cv2.INTER_AREA) if resize.scale != 1.0 else image
        for _, image in read_frames(info.path, frames)
    ]
    stack = np.stack(images)
    median = np.empty(stack.shape[1:], np.uint8)
    for row in range(0, stack.shape[1], 64):  # in bands: a 4K stack's median at once needs several GB
        median[row : row + 64] = np.median(stack[:, row : row + 64], axis=0)
    return median


__all__ = ["MotionTest", "background_image", "measure_motion", "sample_frames"]
