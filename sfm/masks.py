"""Feature masks that keep the moving subject out of the background model (COLMAP: 0 = no features there).

From 2D tracks: the convex hull of a frame's tracked points, dilated by `radius` pixels, plus a disc around
each
point. From user images: `<dir>/<video>/<frame:06d>.png` for one frame or `<dir>/<video>.png` for all frames
of a
video; black (0) marks the moving subject, anything else the static background.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from dynrecon.errors import InputError
from sfm.frames import Resize
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def mask_from_points(points: np.ndarray, resize: Resize, radius: float) -> np.ndarray:
    """(H, W) uint8 mask in SfM pixels: 0 within `radius` (original pixels) of the points' hull, 255
    elsewhere.

    points: (P, 2) original pixels."""
    mask = np.full((resize.height, resize.width), 255, np.uint8)
    if len(points) == 0:
        return mask
    small = np.round(resize.to_small(points)).astype(np.int32)
    r = max(1, round(radius * resize.scale))
    if len(small) >= 3:
        hull = cv2.convexHull(small)
        cv2.fillConvexPoly(mask, hull, 0)
        cv2.polylines(mask, [hull], True, 0, thickness=2 * r)
    for x, y in small:
        cv2.circle(mask, (int(x), int(y)), r, 0, -1)
    return mask


def track_points(tracks: Tracks, video: str) -> dict[int, np.ndarray]:
    """Tracked points per frame of one video: frame -> (P, 2) original pixels."""
    rows = np.array([v == video for v in tracks.video], dtype=bool)
    frames = tracks.frame[rows]
    xy = tracks.xy[rows]
    return {int(f): xy[frames == f] for f in np.unique(frames)}


MASK_LAYOUT = "<folder>/<video>/<frame:06d>.png for one frame or <folder>/<video>.png for all of a video's frames"
ASPECT_TOLERANCE = 0.02  # a mask whose width / height differs more is of another image


def check_mask_folder(mask_dir: Path, videos: list[str]) -> None:
    """The `--masks` folder exists and holds a mask of at least one of `videos` (else a name or path is wrong)."""
    if not mask_dir.is_dir():
        raise InputError(mask_dir, "masks folder not found", fix=f"give a folder with {MASK_LAYOUT}")
    if not any((mask_dir / video).is_dir() or (mask_dir / f"{video}.png").is_file() for video in videos):
        raise InputError(
            mask_dir, f"holds no mask of the videos {', '.join(videos)}", fix=f"name the masks {MASK_LAYOUT}"
        )


def user_mask(mask_dir: Path, video: str, frame: int, resize: Resize) -> np.ndarray | None:
    """The user's mask for this frame (resized to SfM pixels), or None when there is none."""
    for path in (mask_dir / video / f"{frame:06d}.png", mask_dir / f"{video}.png"):
        if path.exists():
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise InputError(path, "cannot read the mask image", fix="masks must be PNG images")
            height, width = image.shape
            if abs(width * resize.height / (height * resize.width) - 1) > ASPECT_TOLERANCE:
                raise InputError(
                    path,
                    f"the mask is {width}x{height}, another shape than its video's {resize.width}x{resize.height} "
                    "SfM images",
                    fix="masks have the video's size (black: the moving subject)",
                )
            if resize.scale != 1.0 or image.shape != (resize.height, resize.width):
                image = cv2.resize(image, (resize.width, resize.height), interpolation=cv2.INTER_NEAREST)
            return np.where(image > 0, 255, 0).astype(np.uint8)
    return None


def write_mask(mask_dir: Path, name: str, mask: np.ndarray) -> None:
    """COLMAP looks for the mask of image `name` at `<mask_dir>/<name>.png`."""
    path = mask_dir / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), mask)
