"""A hint for videos that show a calibration board when no tracks were given: ArUco markers in a few frames.

Registration without tracks cannot use a board it does not know (its squares and size are in the board's file), but
it can say that one is in view: a user filming a ChArUco board then learns that `--board charuco.toml` makes its
corners the subject's tracks.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from dynrecon import video_io
from dynrecon.errors import InputError

log = logging.getLogger(__name__)

# The families boards are printed with (each *_1000 dictionary holds the smaller ones of its family).
DICTIONARIES = (
    "DICT_4X4_1000",
    "DICT_5X5_1000",
    "DICT_6X6_1000",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
    "DICT_APRILTAG_36h11",
)
SAMPLES = 3  # frames looked at per video, spread over it
LONG_SIDE = 1280  # frames are looked at this large at most (the probe's cost)
MIN_MARKERS = 3  # distinct markers of one dictionary in one frame: a board, not a chance pattern


def _detectors() -> dict[str, cv2.aruco.ArucoDetector]:
    params = cv2.aruco.DetectorParameters()
    params.detectInvertedMarker = True  # either print, in one pass: the look needs the ids, not the corners
    return {
        name: cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), params)
        for name in DICTIONARIES
    }


def ids_in_view(grays: Sequence[np.ndarray]) -> dict[str, list[int]]:
    """dictionary -> the marker ids seen, for the dictionaries some of the (H, W) uint8 frames shows MIN_MARKERS
    or more distinct markers of."""
    detectors = _detectors()
    found: dict[str, set[int]] = {}
    for gray in grays:
        for name, detector in detectors.items():
            _, ids, _ = detector.detectMarkers(gray)
            seen = set() if ids is None else {int(i) for i in np.ravel(ids)}
            if len(seen) >= MIN_MARKERS:
                found.setdefault(name, set()).update(seen)
    return {name: sorted(ids) for name, ids in found.items()}


def markers_in_view(paths: Sequence[Path]) -> dict[str, dict[str, list[int]]]:
    """dictionary -> video name -> the marker ids seen, for the dictionaries some sampled frame of a video shows
    MIN_MARKERS or more distinct markers of (printed either way: black on white or inverted)."""
    found: dict[str, dict[str, list[int]]] = {}
    for path in paths:
        try:
            capture = video_io.open_video(path)
        except InputError:  # a hint only: a video that does not open was reported by the probe already
            continue
        grays = []
        try:
            count = video_io.expected_frames(capture) or 0
            for k in range(SAMPLES if count else 0):
                capture.set(cv2.CAP_PROP_POS_FRAMES, int((k + 0.5) * count / SAMPLES))
                image = video_io.read(capture)
                if image is None:
                    continue
                gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                scale = LONG_SIDE / max(gray.shape)
                if scale < 1:
                    gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                grays.append(gray)
        finally:
            capture.release()
        for name, ids in ids_in_view(grays).items():
            found.setdefault(name, {})[path.stem] = ids
    return found


def board_hint(paths: Sequence[Path]) -> str | None:
    """One sentence naming the markers in view and what to give, or None when no video shows markers."""
    found = markers_in_view(paths)
    if not found:
        return None
    name = max(found, key=lambda n: len(found[n]))
    videos = found[name]
    counts: dict[int, int] = {}
    for seen in videos.values():
        for i in seen:
            counts[i] = counts.get(i, 0) + 1
    # ids seen by two videos or more: a camera behind a two-sided board reads mirrored markers as other ids
    ids = sorted(i for i, n in counts.items() if n >= 2 or len(videos) == 1) or sorted(counts)
    shown = f"{ids[0]}-{ids[-1]}" if len(ids) > 6 else ", ".join(map(str, ids))
    log.info("ArUco markers %s (ids %s) in %s", name, shown, ", ".join(videos))
    return (
        f"{len(videos)} video(s) ({', '.join(sorted(videos)[:6])}) show ArUco markers ({name}, ids {shown}): if they "
        "are a ChArUco board, give its file (--board charuco.toml) and its corners become the tracks"
    )


__all__ = ["board_hint", "ids_in_view", "markers_in_view"]
