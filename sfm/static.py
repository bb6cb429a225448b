"""Is a video's camera static? And if so, its one background image for SfM.

A camera on a tripod sees the same background in every frame: sending its frames to SfM as separate images only
adds zero-baseline pairs, which split models and cost most of the matching time. One background image per static
video (the temporal median of sampled frames, in which a moving subject disappears) is matched across videos
instead, and every frame of the video takes that image's pose.

The test: background corners of the median image are tracked (pyramidal LK, forward-backward check) into each
sampled frame. A static camera leaves them where they are; a handheld one moves them all. Pixels where the frames
differ from the median most of the time (the moving subject) are masked out first, and so is where the tracked
subject usually is (a board held in front of a tripod stays in the median). In each sampled frame the corners the
tracked subject covers then are left out: a sample where it hides most of them says nothing about the camera.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from sfm.frames import Resize
from sfm.masks import mask_from_points
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
USUAL = 0.3  # the tracked subject covers a pixel in this share of the samples: it is part of the median image
HIDDEN = 0.5  # a sample whose tracked subject covers more of the corners is not evidence either way
# displaced samples between samples at rest that track under this share of what those track: the corners that moved
# are on something passing in front of the lens (an arm), the background's being lost (`_occlusions`)
OCCLUDED = 2 / 3


@dataclass(kw_only=True)
class MotionTest:
    """The measured decision for one video; `shifts`: median corner displacement per sampled frame (pixels of the
    original video)."""

    static: bool
    reason: str
    frames: list[int] = field(default_factory=list)
    shifts: list[float] = field(default_factory=list)
    tracked: list[float] = field(default_factory=list)  # share of the visible corners tracked per sampled frame
    hidden: list[int] = field(default_factory=list)  # sampled frames where the tracked subject hid most corners
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
            "hidden_by_subject": self.hidden,
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


def _subject_masks(
    subject: dict[int, np.ndarray] | None, frames: np.ndarray, work: Resize, radius: float
) -> list[np.ndarray] | None:
    """Per sampled frame, (H, W) uint8 at the work size, 0 where the tracked subject is (its points' hull dilated
    by `radius` original pixels; the nearest tracked frame's, within half the samples' spacing: a sample far from
    any tracked frame has nothing masked); None without tracks."""
    if not subject:
        return None
    known = np.array(sorted(subject))
    reach = (float(np.diff(frames).min()) - 1) / 2 if len(frames) > 1 else 0.0  # each tracked frame: one sample
    masks = []
    for f in frames:
        nearest = int(known[np.abs(known - f).argmin()])
        points = subject[nearest] if abs(nearest - f) <= reach else np.zeros((0, 2))
        masks.append(mask_from_points(points, work, radius))
    return masks


SubjectFinder = Callable[[np.ndarray, np.ndarray, float], "dict[int, np.ndarray] | None"]


def measure_motion(
    info: ProbedVideo,
    subject: dict[int, np.ndarray] | None = None,
    radius: float = 40.0,
    find_subject: SubjectFinder | None = None,
) -> MotionTest:
    """Measure whether the camera of `info` moves (the sampled frame numbers are in the test's `frames`).

    subject: the tracked subject's points per frame, (P, 2) original pixels (optional); `radius` around them.
    find_subject(frames (S,), grays (S, H, W) at the work size, work scale): the subject's points found in the
    sampled frames themselves, where none are given and the test without them says moving (markers in view, a
    board that fills a tripod's view: sfm/register_markers.py); the test is then made again with them masked."""
    frames = sample_frames(info, SAMPLES)
    work = Resize.for_video(info, WORK_LONG_SIDE)
    grays = np.stack([_gray(image, work) for _, image in read_frames(info.path, frames)])
    if len(frames) < 2:
        return MotionTest(static=False, reason="fewer than 2 frames: treated as moving", frames=frames.tolist())
    measured = _measure(info, frames, grays, work, subject, radius)
    if not measured.static and subject is None and find_subject is not None:
        found = find_subject(frames, grays, work.scale)
        if found is not None:
            measured = _measure(info, frames, grays, work, found, radius)
    return measured


def _measure(
    info: ProbedVideo,
    frames: np.ndarray,
    grays: np.ndarray,
    work: Resize,
    subject: dict[int, np.ndarray] | None,
    radius: float,
) -> MotionTest:
    """The motion test on the sampled frames `grays` (S, H, W) at the work size, `subject` masked."""
    median = np.median(grays, axis=0).astype(np.uint8)
    mask = np.where(_moving_pixels(grays, median), 0, 255).astype(np.uint8)
    covers = _subject_masks(subject, frames, work, radius)
    if covers is not None:
        usual = np.mean([c == 0 for c in covers], axis=0) >= USUAL
        mask[usual] = 0
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
    shifts, tracked, hidden, good_counts = [], [], [], []
    pixels = np.clip(np.round(corners.reshape(-1, 2)).astype(np.int64), 0, [median.shape[1] - 1, median.shape[0] - 1])
    for k, gray in enumerate(grays):
        moved, status, _ = cv2.calcOpticalFlowPyrLK(median, gray, corners, None, **lk)  # type: ignore[call-overload]
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(gray, median, moved, None, **lk)  # type: ignore[call-overload]
        good = (status.ravel() == 1) & (status_back.ravel() == 1)
        good &= np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < 1.0
        visible = np.ones(len(good), bool) if covers is None else covers[k][pixels[:, 1], pixels[:, 0]] > 0
        hidden.append(bool(visible.mean() < 1.0 - HIDDEN))
        good &= visible
        tracked.append(float(good.sum() / max(1, visible.sum())))
        good_counts.append(int(good.sum()))
        shifts.append(_camera_shift(corners.reshape(-1, 2)[good], moved.reshape(-1, 2)[good], gray.shape) * to_original)
    limit = MAX_SHIFT * max(info.width, info.height)
    long_side = max(info.width, info.height)
    # a few corners, too few a share to measure, yet MIN_CORNERS of them where the camera rests: the rest hidden
    # (a person walking away from the camera at the start of a take), not a camera carried
    at_rest = (np.array(good_counts) >= MIN_CORNERS) & (np.array(shifts) <= SETTLED * long_side)
    kinds = _sample_kinds(np.array(shifts), np.array(tracked), np.array(hidden, dtype=bool), limit, at_rest)
    static, reason = _decide(kinds, frames, shifts, tracked, count, limit)
    settled = [
        int(f)
        for f, shift, kind in zip(frames, shifts, kinds, strict=True)
        if kind == REST and shift <= SETTLED * long_side
    ]
    measured = [shift if kind in (REST, DISPLACED) else 0.0 for shift, kind in zip(shifts, kinds, strict=True)]
    moved = _moved(info.name, frames, measured, MOVED * long_side) if static else None
    unmeasured = [int(f) for f, kind in zip(frames, kinds, strict=True) if kind == UNMEASURED]
    if static and len(unmeasured) >= MIN_ODD:
        moved = (f"{moved}; " if moved else "") + (
            f"{info.name}: the background was not seen in sampled frames {', '.join(map(str, unmeasured))} (hidden "
            "by something untracked, or the camera moved): those frames take the static pose"
        )
    return MotionTest(
        static=static,
        reason=reason,
        frames=frames.tolist(),
        shifts=shifts,
        tracked=tracked,
        corners=count,
        settled=settled,
        hidden=[int(f) for f, h in zip(frames, hidden, strict=True) if h],
        moved=moved,
    )


# What one sampled frame says about the camera
REST = "rest"  # the background measured where it is in the median
DISPLACED = "displaced"  # the background measured elsewhere: the camera moved
UNMEASURED = "unmeasured"  # too few corners tracked to measure (occluded, blurred, or moved far)
HIDDEN_KIND = "hidden"  # the tracked subject covers most corners: not evidence either way


def _sample_kinds(
    shifts: np.ndarray, tracked: np.ndarray, hidden: np.ndarray, limit: float, at_rest: np.ndarray | None = None
) -> list[str]:
    """A measured displacement is evidence even where the tracked subject hides most corners; tracked corners
    with no rigid group among them (an infinite shift) count as displaced, as before the subject was known.
    `at_rest` (S,): samples whose tracked corners, under MIN_TRACKED of them, are enough to place the camera at its
    main position: at rest, partly hidden."""
    rest = np.zeros(len(shifts), dtype=bool) if at_rest is None else at_rest
    kinds = []
    for shift, share, h, placed in zip(shifts, tracked, hidden, rest, strict=True):
        if share >= MIN_TRACKED and shift > limit and (np.isfinite(shift) or not h):
            kinds.append(DISPLACED)
        elif h:
            kinds.append(HIDDEN_KIND)
        else:
            kinds.append(REST if share >= MIN_TRACKED or placed else UNMEASURED)
    return _occlusions(kinds, tracked, hidden)


def _occlusions(kinds: list[str], tracked: np.ndarray, hidden: np.ndarray) -> list[str]:
    """Displaced samples that lost corners (under OCCLUDED of the share the samples at rest track), in a run shorter
    than MOVED_RUN with samples at rest on both sides: something passed in front of the lens (an arm at a desk
    webcam) and moved the corners it covered, and the camera was where it was before and after. Unmeasured, then;
    a camera moved for good (at the end) or panning stays displaced."""
    resting = [share for share, kind in zip(tracked, kinds, strict=True) if kind == REST]
    usual = float(np.median(resting)) if resting else 0.0
    lost = [
        kind == DISPLACED and share < OCCLUDED * usual and not h
        for kind, share, h in zip(kinds, tracked, hidden, strict=True)
    ]
    out = list(kinds)
    i = 0
    while i < len(kinds):
        if not lost[i]:
            i += 1
            continue
        end = i
        while end + 1 < len(kinds) and lost[end + 1]:
            end += 1
        if end - i + 1 < MOVED_RUN and i > 0 and end + 1 < len(kinds) and kinds[i - 1] == kinds[end + 1] == REST:
            out[i : end + 1] = [UNMEASURED] * (end - i + 1)
        i = end + 1
    return out


def _end_run(kinds: list[str]) -> int:
    """The longest run of unmeasured samples at the start or the end (hidden ones skipped): where a camera was
    carried off or turned away, unlike an occlusion the background comes back from."""
    seen = [kind for kind in kinds if kind != HIDDEN_KIND]
    lead = next((i for i, kind in enumerate(seen) if kind != UNMEASURED), len(seen))
    trail = next((i for i, kind in enumerate(reversed(seen)) if kind != UNMEASURED), len(seen))
    return max(lead, trail)


def _decide(
    kinds: list[str], frames: np.ndarray, shifts: list[float], tracked: list[float], count: int, limit: float
) -> tuple[bool, str]:
    """Static or moving, and why. One odd sample (a damaged or smeared frame, a flash, a knock) does not make a
    camera move: a moving one is displaced in several samples. Unmeasured samples without a displaced one make it
    move when they are over a third of the samples, or MOVED_RUN of them open or close the video: a person
    standing close to a tripod hides its corners in a few samples and the background comes back where it was,
    while a handheld camera's corners are measured displaced or lost in most."""
    n = {kind: kinds.count(kind) for kind in (REST, DISPLACED, UNMEASURED, HIDDEN_KIND)}
    seen = len(kinds) - n[HIDDEN_KIND]
    odd = [i for i, kind in enumerate(kinds) if kind in (DISPLACED, UNMEASURED)]
    if n[HIDDEN_KIND] and seen <= MIN_ODD:
        return False, (
            f"the tracked subject hides the background in {n[HIDDEN_KIND]} of {len(frames)} sampled frames: "
            "treated as moving"
        )
    # one displaced sample with another unmeasured one is a move in a short video, but among many at rest an arm
    # passing close to the lens (a desk webcam): its corners on the arm are measured displaced, once
    if n[DISPLACED] >= MIN_ODD or (n[DISPLACED] and len(odd) >= max(MIN_ODD, seen / 3)):
        worst = max((i for i in odd if kinds[i] == DISPLACED), key=lambda i: shifts[i])
        return False, (
            f"moving: background shifted {shifts[worst]:.1f} px at frame {int(frames[worst])} (> {limit:.1f} px)"
        )
    if n[UNMEASURED] >= MIN_ODD and (n[UNMEASURED] > seen / 3 or _end_run(kinds) >= MOVED_RUN):
        at = min(odd, key=lambda i: tracked[i])
        return (
            False,
            f"moving: only {tracked[at]:.0%} of {count} background corners tracked into frame {int(frames[at])}",
        )
    steady = [shifts[i] for i, kind in enumerate(kinds) if kind == REST]
    reason = f"static: background shifts at most {max(steady, default=0.0):.2f} px over {len(frames)} sampled frames"
    if n[HIDDEN_KIND]:
        reason += f" ({n[HIDDEN_KIND]} hidden by the tracked subject)"
    if len(odd) == 1:
        at = odd[0]
        reason += (
            f" (one odd sample ignored: frame {int(frames[at])}, {shifts[at]:.1f} px, {tracked[at]:.0%} of the "
            "corners tracked)"
        )
    elif odd:
        reason += f" ({len(odd)} odd samples ignored: frames {', '.join(str(int(frames[i])) for i in odd)})"
    return True, reason


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
