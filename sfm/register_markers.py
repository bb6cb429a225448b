"""Tracks `register` finds itself: fiducial markers in view, where no tracks were given.

A calibration board (ChArUco, an AprilTag grid) or markers on the subject name their corners alike in every video
by the markers' ids: their corners are the subject's tracks without a board file (tracking/markers.py). Where the
background left a static video out, `tracks_from_markers` searches every video with the dictionary that
`sfm.board_hint.markers_in_view` finds in the most videos, cut to the smallest of its family that holds the ids it
saw; ids seen by one video only are left out (they pose nothing, and a mirrored marker can read as another id). The
tracks go to WS/marker_tracks.csv, and the report's `subject.markers` says where the tracks came from.
`markers_in_samples` finds moving markers in the motion test's own sampled frames, for it to mask.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from sfm.board_hint import ids_in_view, markers_in_view
from sfm.options import ALL_CORES
from sfm.plan import VideoPlan
from tracking.markers import find_markers, marker_detector, marker_tracks
from tracking.tracks import Tracks, read_tracks, write_tracks

log = logging.getLogger(__name__)

MARKER_TRACKS = "marker_tracks.csv"
MIN_VIDEOS = 2  # videos that must show the markers for them to pose anything


def tracks_from_markers(
    videos: list[VideoPlan], out: Path, threads: int = ALL_CORES
) -> tuple[Tracks | None, dict[str, Any] | None]:
    """The corners of the markers in view as tracks (written to `out`/marker_tracks.csv), and the report's note
    on them; (None, None) when fewer than MIN_VIDEOS videos show markers of one dictionary. Every video is searched
    (a camera may see a waved board only between the look's samples), in `threads` threads (ALL_CORES: one per
    core)."""
    found = markers_in_view([v.info.path for v in videos])
    if not found:
        return None, None
    dictionary = max(found, key=lambda name: len(found[name]))
    if len(found[dictionary]) < MIN_VIDEOS:
        return None, None
    seen = [i for ids in found[dictionary].values() for i in ids]
    shared = [i for i in seen if seen.count(i) >= MIN_VIDEOS] or seen  # a stray or lone marker sets no size
    dictionary = smallest_dictionary(dictionary, max(shared))
    workers = None if threads == ALL_CORES else threads
    tracks = _shared(marker_tracks([v.info.path for v in videos], dictionary, workers=workers))
    if not len(tracks.video):
        return None, None
    path = out / MARKER_TRACKS
    write_tracks(path, tracks)
    # read back: this run sees the CSV's rounded positions, as a later run given the file will
    tracks = read_tracks(path).canonical()
    rows = np.asarray(tracks.video)
    frames = {name: len(np.unique(tracks.frame[rows == name])) for name in tracks.video_names()}
    log.info(
        "no tracks given: the corners of the %s markers in %s are the subject's tracks (%s)",
        dictionary,
        ", ".join(sorted(frames)),
        path,
    )
    note = {"dictionary": dictionary, "file": str(path), "frames": frames, "points": len(set(tracks.point))}
    return tracks, note


SIZES = (50, 100, 250, 1000)  # OpenCV's predefined dictionaries of one family: each the first codes of the next
ID_MARGIN = 1.5  # the look sees a few frames: a board's ids may run this far past the largest it saw


def smallest_dictionary(dictionary: str, largest_id: int) -> str:
    """The smallest dictionary of `dictionary`'s family (DICT_4X4_50 ... _1000) that holds ids up to ID_MARGIN x
    `largest_id`: it reads the same markers up to 15x faster, corrects a bit more, and reads fewer textures as
    stray markers. Other dictionaries (AprilTag, the original ArUco) are kept."""
    family, _, size = dictionary.rpartition("_")
    if not size.isdigit() or not family.startswith("DICT_") or "X" not in family:
        return dictionary
    needed = max(largest_id + 1, int(np.ceil(ID_MARGIN * (largest_id + 1))))
    return next((f"{family}_{n}" for n in SIZES if n >= needed and n <= int(size)), dictionary)


LOOKS = 3  # sampled frames the motion test's look for markers tries the dictionaries on
STILL = 0.01  # markers that move less over the samples (fraction of the long side) stand still


def markers_in_samples(frames: np.ndarray, grays: np.ndarray, scale: float) -> dict[int, np.ndarray] | None:
    """Where markers are in the motion test's sampled frames (`grays` (S, H, W) at `scale` of the original), as
    frame -> (P, 2) corners in original pixels, so that the test masks them like a tracked subject: a board that
    fills a tripod's view moves rigidly, and the test took its motion for the camera's (sleap-anipose's top
    clip). None without markers in view. The frames are the test's own (small: a mask needs no subpixel corners)."""
    found = ids_in_view([grays[k] for k in np.linspace(0, len(grays) - 1, LOOKS).round().astype(int)])
    if not found:
        return None
    dictionary = max(found, key=lambda name: len(found[name]))
    detector = marker_detector(smallest_dictionary(dictionary, max(found[dictionary])))
    corners: dict[int, np.ndarray] = {}
    where: dict[int, list[np.ndarray]] = {}  # marker id -> its first corner in each sample that shows it
    for frame, gray in zip(frames, grays, strict=True):
        prints = [find_markers(gray, detector, inverted) for inverted in (False, True)]
        shown = [p for p in prints if p is not None]
        if shown:
            ids, xy, _ = max(shown, key=lambda p: len(p[0]))
            corners[int(frame)] = (xy.reshape(-1, 2) + 0.5) / scale - 0.5
            for marker, quad in zip(ids, xy, strict=True):
                where.setdefault(int(marker), []).append(quad[0] / scale)
    moved = [np.ptp(np.array(seen), axis=0).max() for seen in where.values() if len(seen) >= 2]
    if not moved or max(moved) < STILL * grays.shape[2] / scale:
        return None  # markers that stay put are background (a poster of tags), not a subject to mask
    return corners


def _shared(tracks: Tracks) -> Tracks:
    """Only the markers that two videos or more saw."""
    marker = np.array([p.rsplit("_", 1)[0] for p in tracks.point])
    videos = np.asarray(tracks.video)
    seen_by: dict[str, set[str]] = {}
    for m, v in zip(marker, videos, strict=True):
        seen_by.setdefault(m, set()).add(v)
    return tracks.take(np.flatnonzero([len(seen_by[m]) >= MIN_VIDEOS for m in marker]))


__all__ = ["MARKER_TRACKS", "markers_in_samples", "smallest_dictionary", "tracks_from_markers"]
