"""One tracking step, frame t -> t+1 (or t-1), for a batch of points: LK with a forward-backward check, the
CSRT fallback, and the appearance check against the label's patch."""

from __future__ import annotations

import cv2
import numpy as np

from tracking.options import TrackOptions

LK_LEVELS = 3  # LK pyramid levels above the full image


def _lk_params(options: TrackOptions) -> dict:
    return {
        "winSize": (options.win_size, options.win_size),
        "maxLevel": LK_LEVELS,
        "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    }


def lk_step(
    prev: np.ndarray, cur: np.ndarray, xy: np.ndarray, options: TrackOptions, guess: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Track `xy: (N, 2)` from `prev` to `cur` (both (H, W) uint8).

    Returns `new_xy: (N, 2)` and `fb_error: (N,)` pixels (inf where LK lost the point either way).
    `guess: (N, 2)` is an initial position in `cur` (from the fallback); then LK only refines it.
    """
    if len(xy) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    params = _lk_params(options)
    p0 = xy.astype(np.float32).reshape(-1, 1, 2)
    if guess is None:
        p1, st, _ = (np.asarray(a) for a in cv2.calcOpticalFlowPyrLK(prev, cur, p0, p0.copy(), **params))
    else:
        start = guess.astype(np.float32).reshape(-1, 1, 2).copy()
        p1, st, _ = (
            np.asarray(a)
            for a in cv2.calcOpticalFlowPyrLK(prev, cur, p0, start, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params)
        )
    # The backward check starts from the original point, so LK's own basin decides, not the guess.
    p0r, st_b, _ = (
        np.asarray(a)
        for a in cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params)
    )
    fb = np.linalg.norm((p0r - p0).reshape(-1, 2), axis=1).astype(float)
    fb[(st.ravel() == 0) | (st_b.ravel() == 0) | ~np.isfinite(fb)] = np.inf
    return p1.reshape(-1, 2).astype(float), fb


def patch_at(gray: np.ndarray, xy: np.ndarray, size: int) -> np.ndarray:
    """The (size, size) float32 patch centred on sub-pixel `xy: (2,)`."""
    return cv2.getRectSubPix(gray, (size, size), (float(xy[0]), float(xy[1])), patchType=cv2.CV_32F)


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalized cross-correlation of two equal-size patches, in [-1, 1]; 0 when either is flat."""
    a = a - a.mean()
    b = b - b.mean()
    denom = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 1e-6 else 0.0


def csrt_step(prev: np.ndarray, cur: np.ndarray, xy: np.ndarray, box: int) -> np.ndarray | None:
    """Move `xy: (2,)` from `prev` to `cur` with a CSRT tracker on a `box`-sided square around it; None if
    CSRT reports failure or the box would leave the image. Integer precision (the caller refines with LK)."""
    height, width = prev.shape[:2]
    x0 = round(float(xy[0]) - (box - 1) / 2)
    y0 = round(float(xy[1]) - (box - 1) / 2)
    if x0 < 0 or y0 < 0 or x0 + box > width or y0 + box > height:
        return None
    tracker = cv2.TrackerCSRT.create()
    tracker.init(prev, (x0, y0, box, box))
    ok, (x1, y1, w1, h1) = tracker.update(cur)
    if not ok:
        return None
    # Box centres, not corners: CSRT may change the box size (scale estimation) around the same centre.
    shift = np.array([x1 + (w1 - 1) / 2 - (x0 + (box - 1) / 2), y1 + (h1 - 1) / 2 - (y0 + (box - 1) / 2)])
    return np.asarray(xy, dtype=float) + shift


def brightness(gray: np.ndarray) -> tuple[float, float]:
    """(mean, standard deviation) of a frame's gray levels."""
    mean, std = cv2.meanStdDev(gray)
    return float(mean[0, 0]), max(float(std[0, 0]), 1.0)


def normalize_brightness(gray: np.ndarray, reference: tuple[float, float]) -> np.ndarray:
    """(H, W) uint8 with the frame's mean and contrast mapped to `reference` = (mean, std).

    LK assumes a point keeps its brightness between frames; a phone's auto exposure changes the gain of the
    whole frame, which LK would take for motion. A global gain and offset cancel here exactly. Frames within
    2% of the reference are returned as they are: re-quantizing them would only add rounding noise.
    """
    mean, std = brightness(gray)
    scale = reference[1] / std
    offset = reference[0] - scale * mean
    if abs(scale - 1.0) < 0.02 and abs(offset) < 0.02 * reference[0]:
        return gray
    return cv2.convertScaleAbs(gray, alpha=scale, beta=offset)
