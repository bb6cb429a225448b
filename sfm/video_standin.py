"""Videos that are not here: what `import-calibration` needs of each (name, frame count, frame times, image size)
from the tracks and the user, for a lab that shares its calibration and 2D tracks without the videos.

A video given by name (no such file) with `--fps` gets frames 0 to the last tracked frame of that name in the
tracks, at frame / fps (a constant-rate decoder's times; one rate for all, or one per name), and its camera's
calibrated image size, or `--size`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dynrecon.arguments import parse_size
from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES, video_name
from sfm.video import ProbedVideo

__all__ = ["parse_size", "stand_in_videos", "with_size"]

log = logging.getLogger(__name__)


def stand_in_videos(
    values: Sequence[str | Path], tracks: Path | None, fps: float | dict[str, float] | None, tracks_given: bool = False
) -> list[ProbedVideo | None]:
    """For each VIDEO value: None where it is a file (probed as usual), else a stand-in of that name with its
    frames from `tracks` at `fps` (width and height 0 until `with_size`). One-line errors name what is missing;
    `tracks_given`: --tracks or --size was given, which without `fps` serve nothing (a warning)."""
    if fps is None:
        if tracks_given:
            log.warning("--tracks and --size only serve videos that are not here, given with --fps: ignored")
        for value in values:
            path = Path(value)
            if not path.exists() and path.suffix.lower() not in VIDEO_SUFFIXES:  # a name, not a file's path
                raise InputError(
                    path,
                    "no such video",
                    fix="give the video file; where the videos are not here, give --fps and the tracks (--tracks): "
                    "the frames are the tracks' of that name",
                )
        return [None] * len(values)
    for rate in fps.values() if isinstance(fps, dict) else [fps]:
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(None, f"--fps {rate:g}: a frame rate must be a positive number of frames per second")
    missing = [Path(v) for v in values if not Path(v).is_file()]
    for path in missing:  # a path or a file name that is no file is a typo, not a video that is not here
        if path.parent != Path(".") or path.suffix.lower() in VIDEO_SUFFIXES:
            raise InputError(
                path,
                "no such video file",
                fix=f"check the path; a video that is not here is given by its bare name ({video_name(path)}) with "
                "--fps",
            )
    if isinstance(fps, dict):
        fps = {video_name(Path(key)): rate for key, rate in fps.items()}  # cam0.mp4=30 is cam0's rate
        unused = sorted(set(fps) - {video_name(p) for p in missing})
        if unused:
            log.warning(
                "--fps %s: no video given by that name is missing: ignored (a file's rate is read from it)",
                ", ".join(unused),
            )
    if not missing:
        return [None] * len(values)
    if tracks is None or not tracks.is_file():
        where = f"{tracks} not found" if tracks is not None else "no tracks given"
        raise InputError(
            missing[0],
            f"no such video, and its frames cannot come from the tracks ({where})",
            fix="give the tracks with --tracks (or put tracks.csv in --out's workspace first: import-tracks)",
        )
    from tracking.tracks import matched_to_videos, read_tracks  # pandas: only where videos are stood in

    # the tracks' names spelled like the videos' (Cam_0 for cam0) are theirs, as registration takes them
    track_set = matched_to_videos(read_tracks(tracks), [video_name(Path(v)) for v in values])
    last: dict[str, int] = {}
    for video, frame in zip(track_set.video, track_set.frame, strict=True):
        last[video] = max(last.get(video, -1), int(frame))
    out: list[ProbedVideo | None] = []
    for value in values:
        path = Path(value)
        if path.is_file():
            out.append(None)
            continue
        name = video_name(path)
        if name not in last:
            raise InputError(
                path,
                f"no such video, and {tracks} has no tracks of a video {name!r}",
                fix=f"name the videos as the tracks do: {', '.join(sorted(last)) or 'none'}",
            )
        rate = _rate_of(name, fps, path)
        frames = last[name] + 1
        log.info("%s: not here; %d frames at %g fps from %s", name, frames, rate, tracks)
        out.append(
            ProbedVideo(
                path=path, name=name, width=0, height=0, times=np.arange(frames) / rate, nominal_fps=rate, stand_in=True
            )
        )
    return out


def _rate_of(name: str, fps: float | dict[str, float], path: Path) -> float:
    """The frame rate --fps gives video `name`: the one rate, or its own."""
    if not isinstance(fps, dict):
        return fps
    if name not in fps:
        given = ", ".join(sorted(fps)) or "none"
        raise InputError(
            path,
            f"no such video, and --fps gives no rate for {name!r} (rates for: {given})",
            fix=f"add {name}=FPS to --fps",
        )
    return fps[name]


def with_size(
    video: ProbedVideo, camera_size: tuple[int, int], size: tuple[int, int] | None, source: Path | None
) -> None:
    """A stand-in's image size: --size, else its camera's calibrated size; an error where neither is known (`source`:
    the calibration file, None where none was given)."""
    width, height = size or camera_size
    if width <= 0 or height <= 0:
        raise InputError(
            source,
            f"video {video.name!r} is not here and "
            + ("the calibration gives no image size for its camera" if source else "nothing gives its image size"),
            fix="give the videos' size with --size WIDTHxHEIGHT"
            + ("" if source else " (or --intrinsics, a calibration file with the cameras' sizes)"),
        )
    video.width, video.height = width, height
