"""Known intrinsics per video for `register --intrinsics`: from a cameras.json, a calib .toml or a .qca
file."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from dynrecon.names import spelled_alike
from sfm.calibration import (
    StaticCamera,
    Units,
    VideoSizeError,
    intrinsics_at_video_size,
    match_cameras,
    read_calibration,
)
from sfm.cameras import VideoCameras, read_cameras
from sfm.video import ProbedVideo

log = logging.getLogger(__name__)
_TURNED: set[tuple[str, str]] = set()  # registration reads the intrinsics in several steps: one warning per video
_MISSING: set[tuple[str, ...]] = set()  # ... and per file's missing videos


def read_intrinsics_file(path: Path) -> None:
    """Read an --intrinsics file only for its mistakes (a one-line InputError), before any video is probed."""
    if path.suffix.lower() == ".json":
        read_cameras(path)
    else:
        read_calibration(path, units=Units.M)


def known_intrinsics(path: Path, infos: list[ProbedVideo]) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """video name -> (K (3, 3), dist or None) in the video's original pixels (OpenCV convention)."""
    if path.suffix.lower() == ".json":
        named = _json_videos(path, infos)
        result: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        for info in infos:
            video = named.get(info.name)
            if video is None:
                continue
            if not video.frames:
                log.warning("%s: video %r has no posed frame to take intrinsics from", path, video.name)
                continue
            first = video.frames[0]
            K = _at_video_size(first.K, (video.width, video.height), info, info.name, path)
            if K is not None:
                result[info.name] = (K, first.dist)
        if not named:  # (named videos whose image does not fit were warned about, and are estimated)
            raise InputError(
                path,
                f"none of the videos {[i.name for i in infos]} is in this file",
                fix="video names must match the file's names",
            )
        missing = [info.name for info in infos if info.name not in named]  # (the others were warned about)
        if missing and (str(path), *missing) not in _MISSING:
            _MISSING.add((str(path), *missing))
            log.warning(
                "%s gives no intrinsics for %s: they are estimated from the data (name the videos as in the file to "
                "use its intrinsics)",
                path,
                ", ".join(missing),
            )
        return result
    result = {}
    for info, camera in zip(infos, _matched_cameras(path, infos), strict=True):
        K = _at_video_size(camera.K, (camera.width, camera.height), info, camera.name, path, camera.cy_plus_height)
        if K is not None:
            result[info.name] = (K, camera.dist)
    return result


def intrinsics_sizes(path: Path, infos: list[ProbedVideo]) -> dict[str, tuple[int, int]]:
    """video name -> the image size (width, height) that `path` (an --intrinsics file) gives its camera, the cameras
    matched over all of `infos` as `known_intrinsics` matches them (for the videos that are not here, `--fps`);
    videos it does not name are left out."""
    if path.suffix.lower() == ".json":
        return {name: (video.width, video.height) for name, video in _json_videos(path, infos).items()}
    return {info.name: (c.width, c.height) for info, c in zip(infos, _matched_cameras(path, infos), strict=True)}


def _json_videos(path: Path, infos: list[ProbedVideo]) -> dict[str, VideoCameras]:
    """video name -> the video of the cameras.json `path` named alike, for each of `infos` that one is (a
    cameras.json may hold more or fewer videos than this capture: those named alike are taken)."""
    videos = read_cameras(path).videos
    named = {}
    for info in infos:
        found = spelled_alike(info.name, [v.name for v in videos])
        if len(found) == 1:
            named[info.name] = next(v for v in videos if v.name == found[0])
    return named


def _matched_cameras(path: Path, infos: list[ProbedVideo]) -> list[StaticCamera]:
    """The cameras of the calibration file `path`, one per video of `infos` (by name, else by order)."""
    # only the intrinsics are taken: the translations' unit does not matter (no guess, no warning about it)
    return match_cameras(read_calibration(path, units=Units.M), infos, path)


def _at_video_size(
    K: np.ndarray, size: tuple[int, int], info: ProbedVideo, name: str, path: Path, cy_plus_height: bool = False
) -> np.ndarray | None:
    """K in the video's pixels, or None where the video is the calibrated image turned (a turned K is a guess: the
    turn's direction is unknown) or cannot be it: its intrinsics are then estimated from the data, said once."""
    try:
        return intrinsics_at_video_size(K, size, info, name, cy_plus_height)
    except VideoSizeError as error:
        if (str(path), info.name) not in _TURNED:
            _TURNED.add((str(path), info.name))
            log.warning("%s: %s; its intrinsics are estimated from the data instead", error.path, error.what)
        return None
