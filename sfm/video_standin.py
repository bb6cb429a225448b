"""Videos that are not here: what `import-calibration` needs of each (name, frame count, frame times, image size)
from the tracks and the user, for a lab that shares its calibration and 2D tracks without the videos.

A video given by name (no such file) with `--fps` gets frames 0 to the last tracked frame of that name in the
tracks, at frame / fps (a constant-rate decoder's times), and its camera's calibrated image size, or `--size`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES, video_name
from sfm.video import ProbedVideo

__all__ = ["parse_size", "stand_in_videos", "with_size"]

log = logging.getLogger(__name__)


def parse_size(value: str) -> tuple[int, int]:
    """--size WxH: positive integers."""
    parts = value.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f"{value!r} is not WIDTHxHEIGHT (e.g. 1280x1024)") from None
    if width <= 0 or height <= 0:
        raise ValueError(f"{value!r}: width and height must be positive")
    return width, height


def stand_in_videos(
    values: Sequence[str | Path], tracks: Path | None, fps: float | None, tracks_given: bool = False
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
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(None, f"--fps {fps:g}: a frame rate must be a positive number of frames per second")
    missing = [Path(v) for v in values if not Path(v).is_file()]
    if not missing:
        return [None] * len(values)
    if tracks is None or not tracks.is_file():
        where = f"{tracks} not found" if tracks is not None else "no tracks given"
        raise InputError(
            missing[0],
            f"no such video, and its frames cannot come from the tracks ({where})",
            fix="give the tracks with --tracks (or put tracks.csv in --out's workspace first: import-tracks)",
        )
    from tracking.tracks import read_tracks  # pandas: only where videos are stood in

    track_set = read_tracks(tracks)
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
        frames = last[name] + 1
        log.info("%s: not here; %d frames at %g fps from %s", name, frames, fps, tracks)
        out.append(ProbedVideo(path=path, name=name, width=0, height=0, times=np.arange(frames) / fps, nominal_fps=fps))
    return out


def with_size(video: ProbedVideo, camera_size: tuple[int, int], size: tuple[int, int] | None, source: Path) -> None:
    """A stand-in's image size: --size, else its camera's calibrated size; an error where neither is known."""
    width, height = size or camera_size
    if width <= 0 or height <= 0:
        raise InputError(
            source,
            f"video {video.name!r} is not here and the calibration gives no image size for its camera",
            fix="give the videos' size with --size WIDTHxHEIGHT",
        )
    video.width, video.height = width, height
