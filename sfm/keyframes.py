"""A moving video's SfM frames chosen by content: a new keyframe where the view has moved enough since the last.

Corners of the last keyframe are tracked frame to frame by pyramidal LK at a small working resolution. A frame
becomes the next keyframe when the tracked corners' median displacement from the keyframe exceeds `motion` (a
share of the long side), or when fewer than `survival` of the keyframe's corners are still tracked (the view has
changed: occlusion, a fast pan, blur). So a slow video sends few frames and a fast one many, each step about the
same parallax. The first and the last frame are always keyframes; `max_frames` caps the count (thinned evenly).
When content chooses fewer than `MIN_KEYFRAMES`, the video is short or barely moves: it sends
min(MIN_KEYFRAMES, max_frames) evenly spaced frames instead (a short clip is cheap, and SfM needs several views).
With `masks` (the moving subject, from its tracks), no corner is started on the subject, and a corner that the
subject covers leaves the count: the subject's own motion and its occlusions do not start keyframes.
"""

from __future__ import annotations

import enum
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from sfm.frames import Resize
from sfm.video import ProbedVideo, read_frames

log = logging.getLogger(__name__)

WORK_LONG_SIDE = 480  # keyframes are chosen on frames of this long side (pixels)
MAX_CORNERS = 200  # corners tracked from each keyframe
MIN_CORNERS = 20  # fewer trackable corners: the view is untextured and cannot start a keyframe by content
MIN_KEYFRAMES = 12  # a video sends at least this many frames (when it has them and max_frames allows)
LK_WINDOW = 21
LK_LEVELS = 3
LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)

Masks = Callable[[int], np.ndarray | None]  # frame -> (H, W) uint8 at any size (0 = subject), or None


class KeyframeReason(enum.Enum):
    """Why a frame was sent to SfM."""

    FIRST = "first"
    MOTION = "motion"  # the median displacement from the last keyframe crossed the threshold
    OVERLAP = "overlap"  # too few of the last keyframe's corners were still tracked
    LAST = "last"
    FILL = "fill"  # evenly spaced: content chose fewer than MIN_KEYFRAMES
    EVEN = "even"  # chosen evenly (--keyframes-by even)


@dataclass(kw_only=True)
class KeyframeChoice:
    """The SfM frames of one video and why each was chosen. `frames` (K,) sorted decoded frame numbers."""

    method: str
    frames: np.ndarray
    reasons: list[KeyframeReason]
    candidates: int  # keyframes content chose before the cap
    thinned: bool = False  # the cap (max_frames) removed some
    settings: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The report's `keyframes` entry of a video (docs/formats.md)."""
        counts = Counter(reason.value for reason in self.reasons)
        return {
            "method": self.method,
            "count": len(self.frames),
            "by_reason": dict(sorted(counts.items())),
            "chosen_by_content": self.candidates,
            "thinned_to_max_frames": self.thinned,
            **self.settings,
            "frames": [int(f) for f in self.frames],
        }


@dataclass
class _Reference:
    """The last keyframe's corners (N, 2) and where they are now (N, 2), working pixels; `alive` (N,) bool;
    `covered` (N,) bool: lost under the subject's mask (not counted as lost overlap)."""

    frame: int
    start: np.ndarray
    now: np.ndarray
    alive: np.ndarray
    covered: np.ndarray | None = None


def even_choice(frames: np.ndarray) -> KeyframeChoice:
    """Today's evenly sampled frames (`select_frames`), in the report's terms."""
    return KeyframeChoice(
        method="even", frames=frames, reasons=[KeyframeReason.EVEN] * len(frames), candidates=len(frames)
    )


def choose_keyframes(
    info: ProbedVideo,
    *,
    motion: float,
    survival: float,
    max_frames: int,
    masks: Masks | None = None,
    desc: str = "choosing keyframes",
) -> KeyframeChoice:
    """Keyframes of a moving video by measured motion along it (one decoding pass at WORK_LONG_SIDE); `masks`
    keeps the moving subject out of the measure."""
    work = Resize.for_video(info, WORK_LONG_SIDE)
    threshold = motion * max(work.width, work.height)
    chosen: dict[int, KeyframeReason] = {}
    previous: np.ndarray | None = None
    reference: _Reference | None = None
    frames = np.arange(info.num_frames)
    for frame, image in tqdm(
        read_frames(info.path, frames), total=len(frames), desc=f"{desc} {info.name}", unit="frame", leave=False
    ):
        grey = _grey(image, work)
        background = _background(masks(frame) if masks is not None else None, grey.shape)
        if reference is None or previous is None:
            chosen[frame] = KeyframeReason.FIRST
            reference = _start(frame, grey, background)
        else:
            _follow(reference, previous, grey, background)
            reason = _reason(reference, threshold, survival)
            if reason is not None:
                chosen[frame] = reason
                reference = _start(frame, grey, background)
            elif len(reference.start) < MIN_CORNERS:
                # Untextured so far: look again, no keyframe by content.
                reference = _start(reference.frame, grey, background)
        previous = grey
    chosen.setdefault(info.num_frames - 1, KeyframeReason.LAST)
    return _bounded(chosen, info.num_frames, max_frames, {"motion": motion, "survival": survival})


def _grey(image: np.ndarray, work: Resize) -> np.ndarray:
    """(h, w) uint8 grey frame at the working resolution."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    if work.scale != 1.0:
        grey = cv2.resize(grey, (work.width, work.height), interpolation=cv2.INTER_AREA)
    return grey


def _background(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
    """(h, w) uint8 at the working resolution, 255 where an LK window around a pixel does not reach the subject
    (as goodFeaturesToTrack wants), or None."""
    if mask is None:
        return None
    if mask.shape != shape:
        mask = cv2.resize(mask, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    # A corner whose window sees the subject's edge is dragged along by it, never covered.
    return cv2.erode(np.where(mask > 0, 255, 0).astype(np.uint8), np.ones((LK_WINDOW, LK_WINDOW), np.uint8))


def _start(frame: int, grey: np.ndarray, background: np.ndarray | None = None) -> _Reference:
    """A new reference at `frame`: its corners (off the subject), all alive."""
    spacing = max(grey.shape) / 40
    corners = cv2.goodFeaturesToTrack(
        grey, maxCorners=MAX_CORNERS, qualityLevel=0.01, minDistance=spacing, mask=background
    )
    points = np.zeros((0, 2)) if corners is None else np.asarray(corners, float).reshape(-1, 2)
    return _Reference(
        frame=frame,
        start=points,
        now=points.copy(),
        alive=np.ones(len(points), bool),
        covered=np.zeros(len(points), bool),
    )


def _follow(
    reference: _Reference, previous: np.ndarray, current: np.ndarray, background: np.ndarray | None = None
) -> None:
    """Carry the reference's live corners from `previous` into `current` (forward LK, status and bounds); those
    that the subject covers (in `previous`, where LK would follow it, or in `current`) stop, as covered."""
    live = np.flatnonzero(reference.alive)
    if len(live) == 0:
        return
    p0 = reference.now[live].astype(np.float32).reshape(-1, 1, 2)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        previous, current, p0, p0.copy(), winSize=(LK_WINDOW, LK_WINDOW), maxLevel=LK_LEVELS, criteria=LK_CRITERIA
    )
    new = np.asarray(p1, float).reshape(-1, 2)
    height, width = current.shape
    inside = (new[:, 0] >= 0) & (new[:, 1] >= 0) & (new[:, 0] <= width - 1) & (new[:, 1] <= height - 1)
    kept = (np.asarray(status).ravel() == 1) & inside
    if background is not None:
        before = _on(background, reference.now[live]) | (_on(background, new) & inside)
        if reference.covered is None:
            reference.covered = np.zeros(len(reference.start), bool)
        reference.covered[live] = before
        kept &= ~before
    reference.now[live] = new
    reference.alive[live] = kept


def _on(background: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) bool: the points (N, 2) (working pixels) that fall on the subject (0 in `background`)."""
    x = np.clip(np.round(points[:, 0]).astype(int), 0, background.shape[1] - 1)
    y = np.clip(np.round(points[:, 1]).astype(int), 0, background.shape[0] - 1)
    return np.asarray(background[y, x] == 0)


def _reason(reference: _Reference, threshold: float, survival: float) -> KeyframeReason | None:
    """Why the current frame must be a keyframe, or None. A reference without enough corners decides nothing."""
    if len(reference.start) < MIN_CORNERS:
        return None
    # Corners under the subject are neither kept nor lost: the background behind it has not left the view.
    counted = ~reference.covered if reference.covered is not None else np.ones(len(reference.alive), bool)
    if counted.sum() < MIN_CORNERS:  # the subject has covered nearly all of them: measure again from here
        return KeyframeReason.OVERLAP
    if reference.alive[counted].mean() < survival:
        return KeyframeReason.OVERLAP
    moved = np.linalg.norm(reference.now[reference.alive] - reference.start[reference.alive], axis=1)
    return KeyframeReason.MOTION if float(np.median(moved)) > threshold else None


def _bounded(
    chosen: dict[int, KeyframeReason], count: int, max_frames: int, settings: dict[str, float]
) -> KeyframeChoice:
    """The chosen frames capped at `max_frames` (thinned evenly), or evenly spaced ones when there are fewer than
    MIN_KEYFRAMES."""
    frames = np.array(sorted(chosen), dtype=np.int64)
    candidates = len(frames)
    if candidates < MIN_KEYFRAMES:
        wanted = min(MIN_KEYFRAMES, count, max_frames if max_frames > 0 else count)
        frames = np.unique(np.round(np.linspace(0, count - 1, wanted)).astype(np.int64))
        chosen = dict.fromkeys((int(f) for f in frames), KeyframeReason.FILL)
    thinned = 0 < max_frames < len(frames)
    if thinned:
        frames = frames[np.unique(np.round(np.linspace(0, len(frames) - 1, max_frames)).astype(int))]
    return KeyframeChoice(
        method="content",
        frames=frames,
        reasons=[chosen[int(f)] for f in frames],
        candidates=candidates,
        thinned=thinned,
        settings=settings,
    )
