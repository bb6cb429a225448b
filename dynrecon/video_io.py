"""Opening and stepping through video files: the one place that decides how every reader sees a video.

Every reader (probing, the frames sent to SfM, tracking, the labeling page, ChArUco detection) opens and steps
through videos here, so that frame n of a video is the same image, at the same size, everywhere:

- Orientation: frames are upright, as a player shows them. A phone that films in portrait usually stores landscape
  frames with a rotation flag (a display matrix); OpenCV's FFmpeg backend applies it when
  `CAP_PROP_ORIENTATION_AUTO` is on. It is on by default in OpenCV 5.0, and is set here explicitly so that no reader
  depends on that default. Width, height, intrinsics and 2D points are all in the upright frame's pixels.
- Frame numbers: frame n is the n-th frame the decoder returns, from 0. A packet the decoder rejects (a damaged
  stretch) is skipped and decoding goes on after it, where a bare `VideoCapture.read()` loop would stop there.
- Times: the decoder's presentation timestamp of each frame (`CAP_PROP_POS_MSEC`), which FFmpeg takes from the
  container, so variable-frame-rate videos keep their real frame times.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from dynrecon.errors import InputError

log = logging.getLogger(__name__)
# FFmpeg complains once per damaged packet (hundreds of lines for one bad file); the probe's warning says it once.
# Read when OpenCV's FFmpeg backend opens its first video: every reader opens videos here.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

# Consecutive undecodable packets after which a video is taken to have ended (at the end every grab fails at once).
MAX_SKIPPED = 256
# A step between decoded frames longer than this many typical steps means frames are missing there.
GAP_FACTOR = 1.5
# How many missing stretches a warning lists by position before it only counts the rest.
LISTED_GAPS = 3

CANNOT_OPEN_FIX = (
    "it may hold no video stream (a sound recording); if it plays elsewhere it may lack its index because "
    "recording was cut off, or use an unsupported codec (AV1): convert it with ffmpeg -i in -c:v libx264 out.mp4"
)


def check_video_file(path: Path) -> None:
    """One-line errors for a path that cannot be a video, before OpenCV is asked."""
    if path.is_dir():
        images = any(p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp") for p in path.iterdir())
        raise InputError(
            path,
            "is a directory, not a video file" + (" (it holds images: a frame sequence?)" if images else ""),
            fix=f"make a video of the frames first, e.g. ffmpeg -framerate 30 -i {path}/%05d.jpg {path}.mp4"
            if images
            else "give the video files themselves",
        )
    if not path.exists():
        raise InputError(path, "video file not found", fix="check the path")
    if path.stat().st_size == 0:
        raise InputError(path, "file is empty (0 bytes)", fix="copy the video again")


def open_video(path: str | Path) -> cv2.VideoCapture:
    """A capture that returns upright frames; InputError when the file cannot be opened."""
    path = Path(path)
    check_video_file(path)
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InputError(path, "OpenCV cannot open this video", fix=CANNOT_OPEN_FIX)
    if not capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1) and rotation(capture):
        # A backend that cannot rotate would hand out sideways frames under an upright frame's name.
        capture.release()
        raise InputError(path, "has a rotation flag this OpenCV backend cannot apply", fix="re-encode it upright")
    return capture


def grab(capture: cv2.VideoCapture) -> bool:
    """Advance to the next decodable frame, skipping damaged packets; False at the end of the video."""
    return any(capture.grab() for _ in range(MAX_SKIPPED + 1))


def read(capture: cv2.VideoCapture) -> np.ndarray | None:
    """The next decodable frame (BGR, upright), or None at the end of the video."""
    if not grab(capture):
        return None
    ok, image = capture.retrieve()
    return image if ok else None


def expected_frames(capture: cv2.VideoCapture) -> int | None:
    """The container's frame count (its frame index, or duration × frame rate), None when it gives none."""
    count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
    return int(count) if count and count > 0 else None


def rotation(capture: cv2.VideoCapture) -> int:
    """Degrees of the container's rotation flag that the capture applies to each frame (0, 90, 180 or 270)."""
    value = capture.get(cv2.CAP_PROP_ORIENTATION_META)
    return int(value) % 360 if value and value > 0 else 0


def rotated_pixels_message(name: str, degrees: int, source: Path | str) -> str:
    """One line for a video with a rotation flag whose pixels come from a file: they must be the upright frame's."""
    return (
        f"{name}: the video carries a rotation flag of {degrees} degrees, so its frames are read upright (as OpenCV, "
        f"DeepLabCut and ffmpeg show them): the pixels in {source} must be those of the upright frames, not of the "
        "stored ones"
    )


def count_message(
    path: Path, decoded: int, expected: int | None, where: str = "", *, at_end: bool = False
) -> str | None:
    """One line when fewer frames decoded than the container lists (`where`: the missing stretches), else None."""
    if expected is None or decoded >= expected:
        return None
    missing = f"{expected - decoded} missing" + (f" ({where})" if where else "")
    # Where the container has no frame index (MKV, WebM) the count is its duration times the rate, and a sound
    # track that runs on after the picture stops lengthens that duration: a shortfall at the end only may be that.
    cause = "the file is damaged or cut short"
    if at_end:
        cause = "the file is cut short, or its sound runs on after the picture"
    return f"{path}: {decoded} of {expected} frames decoded, {missing}; {cause}, the decoded frames are used"


def missing_message(path: Path, times: np.ndarray, expected: int | None) -> str | None:
    """One line naming the file and where frames are missing (from the gaps in the decoder's timestamps)."""
    if expected is None or len(times) >= expected:
        return None
    parts, at_end = _gaps(np.asarray(times, dtype=float), expected - len(times))
    return count_message(path, len(times), expected, ", ".join(parts), at_end=at_end)


def _gaps(times: np.ndarray, missing: int) -> tuple[list[str], bool]:
    """Stretches of missing frames: inside the video from long steps between timestamps, the rest at the end; and
    whether all of them are at the end."""
    if len(times) < 2:
        return ([f"{missing} after frame 0"], True) if len(times) else ([], False)
    steps = np.diff(times)
    typical = float(np.median(steps))
    if typical <= 0:
        return [], False
    found = []
    if times[0] > GAP_FACTOR * typical:
        found.append((round(times[0] / typical), f"before frame 0 at 0-{times[0]:.2f} s"))
    for i in np.flatnonzero(steps > GAP_FACTOR * typical):
        found.append(
            (round(steps[i] / typical) - 1, f"between frames {i} and {i + 1} at {times[i]:.2f}-{times[i + 1]:.2f} s")
        )
    parts = [f"{count} {place}" for count, place in found[:LISTED_GAPS]]
    if len(found) > LISTED_GAPS:
        parts.append(f"{sum(count for count, _ in found[LISTED_GAPS:])} in {len(found) - LISTED_GAPS} more stretches")
    tail = missing - sum(count for count, _ in found)
    if tail > 0:
        parts.append(f"{tail} after frame {len(times) - 1} at {times[-1]:.2f} s")
    return parts, not found and tail > 0
