"""Fiducial markers' corners as tracks: every ArUco or AprilTag marker of one dictionary in every frame of each
video, no board file needed.

A marker's id names it in every video, so its four corners are points that every camera names alike: a ChArUco
board, an AprilTag grid or markers stuck on a moving object become the subject's tracks without knowing the
board's layout or size. Corners are refined to subpixel by their gradients.

A two-sided board's back face (its mirror print, aligned with the front) is seen mirrored: every frame is also
searched flipped left-right, the corners found are flipped back and named as the front's, which lie in front of
them. The way that finds more markers is kept: a mirror print read unflipped gives a few markers, some under a real
id with their corners in mirrored order (a frame where both ways find as many is left out). An inverted print
(white on black) is searched in the inverted frame, the print found last first; a frame where that print shows
fewer than ENOUGH markers is searched as the other print too, and the print that shows more is kept (a texture
read as one stray marker of one print had won over the board in the other). A marker id some frame shows twice
(two boards printed with the same ids) is left out everywhere: its name would join two points.

Rows of the result: video = the file name without extension, frame = 0-based decoded frame index, point =
`marker_<id>_<k>` (k = 0..3, OpenCV's corner order: clockwise from the marker's top-left), x, y in OpenCV pixels,
`source` = "marker".
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from dynrecon import video_io
from dynrecon.errors import InputError
from dynrecon.names import first_repeated
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

SOURCE_MARKERS = "marker"


def marker_point(marker_id: int, corner: int) -> str:
    return f"marker_{marker_id}_{corner}"


def dictionary_id(name: str, path: Path | None = None, what: str = "marker") -> int:
    """OpenCV's id of the predefined dictionary `name` (DICT_4X4_50, ...); InputError (on `path`, the file that
    named it) for another name."""
    value = getattr(cv2.aruco, name.upper(), None) if name.upper().startswith("DICT_") else None
    if not isinstance(value, int):
        raise InputError(path, f"unknown {what} dictionary {name!r}", fix="use an OpenCV name such as DICT_4X4_50")
    return value


def marker_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    """OpenCV's detector for `dictionary` (a predefined name such as DICT_4X4_1000), markers as printed (black on
    white)."""
    value = dictionary_id(dictionary)
    # Corners are refined by `_refine` (OpenCV's own refinement measured worse); inverted prints are searched in
    # the inverted frame: OpenCV's detectInvertedMarker read a plain marker's inner outline as the marker.
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(value), cv2.aruco.DetectorParameters())


LONG_SIDE = 1280  # frames are searched this large at most; corners are refined in the full frame
MAX_SEARCHED = 3000  # frames searched per video, evenly spaced over a longer one (the search's cost)
ENOUGH = 2  # markers of the print searched first that end a frame's search (fewer: the other print is tried too)


def detect_markers(
    gray: np.ndarray, detector: cv2.aruco.ArucoDetector, *, mirrored: bool = False, inverted: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Marker ids (M,) int64 and corner positions (M, 4, 2) in one (H, W) uint8 frame as the detector finds them
    (unrefined; an id printed twice is there twice); `mirrored`: searched in the frame flipped left-right,
    positions in the frame's own; `inverted`: a white on black print, searched in 255 - frame."""
    image = 255 - gray if inverted else gray
    corners, ids, _ = detector.detectMarkers(cv2.flip(image, 1) if mirrored else image)
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 2))
    ids = np.asarray(ids, dtype=np.int64).ravel()
    xy = np.asarray(corners, dtype=float).reshape(-1, 4, 2)
    if mirrored:
        xy[..., 0] = gray.shape[1] - 1 - xy[..., 0]  # column c of the flipped frame is column W - 1 - c
    return ids, xy


REFINE_PER_SIDE = 12  # the refinement's half window is the marker's side / this: inside its border cell
MIN_WINDOW, MAX_WINDOW = 2, 8  # half window, pixels


def refine_corners(gray: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Each corner (M, 4, 2) moved to the gradients' corner (cv2.cornerSubPix) in a window that stays inside the
    marker's border: the detector's corners lie on the thresholded outline, up to 2 px inside a small marker."""
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.01)
    refined = xy.copy()
    for m, quad in enumerate(xy):
        side = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
        half = int(np.clip(round(side / REFINE_PER_SIDE), MIN_WINDOW, MAX_WINDOW))
        moved = cv2.cornerSubPix(gray, quad.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
        moved = moved.reshape(4, 2).astype(float)
        far = np.linalg.norm(moved - quad, axis=1) > half  # left the window: another edge pulled it
        refined[m] = np.where(far[:, None], quad, moved)
    return refined


def find_markers(
    gray: np.ndarray, detector: cv2.aruco.ArucoDetector, inverted: bool
) -> tuple[np.ndarray, np.ndarray, set[int]] | None:
    """The refined markers (ids (M,), corners (M, 4, 2)) of the face that shows more of them in a full-size frame,
    and the ids it shows twice (left out). Searched as it is and mirrored (a
    mirror print reads as a few markers unmirrored, some with a real id and their corners in mirrored order), in a
    copy at most LONG_SIDE large. None when neither way finds one, or both as many (which face is seen is not
    known)."""
    scale = min(1.0, LONG_SIDE / max(gray.shape))
    small = gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    front = detect_markers(small, detector, inverted=inverted)
    back = detect_markers(small, detector, mirrored=True, inverted=inverted)
    if len(front[0]) == len(back[0]):
        return None
    ids, xy = front if len(front[0]) > len(back[0]) else back
    values, counts = np.unique(ids, return_counts=True)
    once = np.isin(ids, values[counts == 1])
    refined = refine_corners(gray, (xy[once] + 0.5) / scale - 0.5)  # pixel centres at integers in both sizes
    return ids[once], refined, {int(v) for v in values[counts > 1]}


def _detect_video(
    path: Path, dictionary: str, progress: tqdm | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, set[int]]:
    """(frame (N,), marker id (N,), corners (N, 4, 2), decoded frame count, ids some frame showed twice) for one
    video."""
    if not path.is_file():
        raise InputError(path, "video file not found" if not path.exists() else "not a video file")
    capture = video_io.open_video(path)
    detector = marker_detector(dictionary)
    step = max(1, -(-(video_io.expected_frames(capture) or 0) // MAX_SEARCHED))
    frames: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    xy: list[np.ndarray] = []
    doubled: set[int] = set()
    index = 0
    inverted = False  # the print found last is searched first: a board is printed one way
    try:
        while True:
            if index % step:
                if not video_io.grab(capture):
                    break
                index += 1
                continue
            image = video_io.read(capture)
            if image is None:
                break
            gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            best = None
            for print_inverted in (inverted, not inverted):
                found = find_markers(gray, detector, print_inverted)
                if found is not None and (best is None or len(found[0]) > len(best[0][0])):
                    best = (found, print_inverted)
                if best is not None and len(best[0][0]) >= ENOUGH:  # one stray marker does not end the search
                    break
            if best is not None:
                (found_ids, found_xy, found_doubled), inverted = best
                frames.append(np.full(len(found_ids), index, dtype=np.int64))
                ids.append(found_ids)
                xy.append(found_xy)
                doubled |= found_doubled
            index += 1
            if progress is not None:
                progress.update(1)
    finally:
        capture.release()
    if index == 0:
        raise InputError(path, "no decodable frames", fix="check the file plays; convert it to H.264")
    if not frames:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 4, 2)), index, doubled
    return np.concatenate(frames), np.concatenate(ids), np.concatenate(xy), index, doubled


def marker_tracks(
    videos: Sequence[Path | str],
    dictionary: str,
    *,
    workers: int | None = None,
) -> Tracks:
    """The corners of every marker of `dictionary` in every frame of every video
    (evenly spaced frames of a video longer than MAX_SEARCHED): one row per (video, frame, marker, corner), point
    `marker_<id>_<k>`. An id some frame shows twice (two boards printed with the same ids) is left out of every
    video: its name would join two points. Videos are decoded in `workers` threads (default: one per video, at
    most the CPU count); OpenCV releases the GIL while decoding and detecting."""
    paths = [Path(v) for v in videos]
    names = [p.stem for p in paths]
    twice = first_repeated(names)
    if twice is not None:
        raise InputError(paths[twice], f"two videos are named {names[twice]!r}", fix="video names must be unique")
    marker_detector(dictionary)  # an unknown dictionary fails before any decoding
    workers = workers or max(1, min(len(paths), os.cpu_count() or 1))
    with (
        tqdm(desc=f"finding {dictionary} markers", unit="frame", leave=False) as progress,
        ThreadPoolExecutor(max_workers=workers) as pool,
    ):
        results = list(pool.map(lambda p: _detect_video(p, dictionary, progress), paths))
    doubled: set[int] = set().union(*(result[4] for result in results))
    if doubled:
        log.warning(
            "%s markers %s: seen twice in one frame (two boards with the same ids?): left out",
            dictionary,
            ", ".join(map(str, sorted(doubled)[:10])),
        )
    video: list[str] = []
    frame: list[np.ndarray] = []
    point: list[str] = []
    xy: list[np.ndarray] = []
    for name, path, (frames, found, corners, count, _) in zip(names, paths, results, strict=True):
        keep = ~np.isin(found, sorted(doubled))
        frames, found, corners = frames[keep], found[keep], corners[keep]
        log.info(
            "%s: %s markers in %d of %d frames (%d distinct)",
            path,
            dictionary,
            len(np.unique(frames)),
            count,
            len(np.unique(found)),
        )
        video += [name] * (4 * len(frames))
        frame.append(np.repeat(frames, 4))
        point += [marker_point(int(i), k) for i in found for k in range(4)]
        xy.append(corners.reshape(-1, 2))
    return Tracks(
        video=video,
        frame=np.concatenate(frame) if frame else np.zeros(0, dtype=np.int64),
        point=point,
        xy=np.concatenate(xy) if xy else np.zeros((0, 2)),
        extra={"source": [SOURCE_MARKERS] * len(video)},
    )


__all__ = [
    "SOURCE_MARKERS",
    "detect_markers",
    "dictionary_id",
    "find_markers",
    "marker_detector",
    "marker_point",
    "marker_tracks",
    "refine_corners",
]
