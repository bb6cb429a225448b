"""DLTdv's and Argus's digitized 2D points (`*xypts.csv`) as detections.

Layout (from the tools' source; docs/formats.md): a header, then one row per frame of camera 1 (row 1 = frame 1),
NaN where a point was not digitized. DLTdv's columns are `<point>_cam<N>_X`, `_Y` (8.4 on: `_U`, `_V`), point
by point and camera by camera; Argus's `<point>_cam_<N>_x`, `_y`, sorted by name. Columns are read by their names.
The pixels follow the tool (`DltPixels`): DLTdv 5-7 and Argus count rows up from the bottom (the videos' heights
turn them into image rows), DLTdv 8 counts from 1. A sibling `*offsets.csv` (same prefix) gives each camera's
frame offset: row n holds camera i's video frame n + offset (DLTdv's rule, its mean over the digitized rows).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES, video_name
from dynrecon.readers import csv_records, finite_float
from dynrecon.video_io import open_video
from tracking.detections import Detection
from tracking.pixels import DltPixels

log = logging.getLogger(__name__)

DLTDV_COLUMN = re.compile(r"^(?P<point>.+)_cam(?P<camera>\d+)_(?P<axis>[XYUV])$")
ARGUS_COLUMN = re.compile(r"^(?P<point>.+)_cam_(?P<camera>\d+)_(?P<axis>[xy])$")
PIXELS_FIX = (
    "give --pixels dltdv7 (DLTdv 5-7: rows counted up from the bottom) or --pixels dltdv8 (DLTdv 8.0-8.3: from the top)"
)


def _column(name: str) -> re.Match[str] | None:
    return DLTDV_COLUMN.match(name) or ARGUS_COLUMN.match(name)


def is_dltdv_points(header: str) -> bool:
    """Whether a CSV's first line is DLTdv's or Argus's xypts header."""
    first = header.split(",")[0].strip().strip('"')
    return _column(first) is not None


def _pixels(path: Path, header: list[str], pixels: DltPixels) -> DltPixels:
    if pixels is not DltPixels.AUTO:
        return pixels
    if ARGUS_COLUMN.match(header[0]):
        return DltPixels.ARGUS
    if header[0].endswith(("_U", "_V")):  # DLTdv 8.4 on
        return DltPixels.DLTDV8
    raise InputError(
        path,
        "DLTdv's _X/_Y columns count rows up from the bottom in DLTdv 5-7 and down from the top in DLTdv 8.0-8.3",
        where="line 1",
        fix=PIXELS_FIX,
    )


def _heights(path: Path, videos: Sequence[str | Path], cameras: int, pixels: DltPixels) -> list[int | None]:
    """Each camera's video height (None where none is needed or known)."""
    if videos and len(videos) != cameras:
        raise InputError(
            path,
            f"holds {cameras} cameras, but {len(videos)} videos were given",
            fix="give one video per camera, in the file's camera order (cam1 first)",
        )
    if not pixels.from_bottom:
        return [None] * cameras
    if not videos:
        raise InputError(
            path,
            f"{pixels.value}'s rows count up from the bottom of the image, whose height is in no such file",
            fix="give the videos in camera order: --videos cam1.mp4 cam2.mp4 ...",
        )
    heights: list[int | None] = []
    for video in videos:
        if Path(video).suffix.lower() not in VIDEO_SUFFIXES:
            raise InputError(
                Path(video), "is not a video file", fix="give the video files, whose heights turn the rows around"
            )
        capture = open_video(video)
        heights.append(int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        capture.release()
    return heights


def _offsets(path: Path, cameras: int) -> list[int]:
    """Each camera's frame offset from the sibling offsets file (0 without one)."""
    sibling = path.with_name(path.name.replace("xypts", "offsets"))
    if sibling == path or not sibling.is_file():
        return [0] * cameras
    values: list[list[float]] = [[] for _ in range(cameras)]
    for number, fields in csv_records(sibling):
        if number == 1:
            continue  # the header: cam1_offset, ... or camera_1, ...
        for camera, text in enumerate(fields[:cameras]):
            if text.strip().lower() == "nan":
                continue
            value = finite_float(text)
            if value is None:
                raise InputError(sibling, f"{text!r} is not a number", where=f"line {number}")
            if value:  # DLTdv writes 0 where nothing was digitized
                values[camera].append(value)
    offsets = []
    for camera, found in enumerate(values):
        mean = float(np.mean(found)) if found else 0.0
        if abs(mean - round(mean)) > 1e-6:
            log.warning(
                "%s: camera %d's offset %.3g frames is not whole; its points are taken on frame row + %d",
                sibling,
                camera + 1,
                mean,
                round(mean),
            )
        offsets.append(round(mean))
    if any(offsets):
        log.info("%s: frame offsets per camera %s applied", sibling, offsets)
    return offsets


def read_dltdv_points(
    path: str | Path, videos: Sequence[str | Path] = (), pixels: DltPixels = DltPixels.AUTO
) -> list[Detection]:
    """The detections of a DLTdv / Argus xypts file, in OpenCV's pixels. `videos`: one per camera, in order (their
    names name the videos, their heights turn bottom-up rows around); without them cameras are named cam1..."""
    path = Path(path)
    records = csv_records(path)
    try:
        _, header = next(records)
    except StopIteration:
        raise InputError(path, "the file is empty") from None
    header = [h.strip().strip('"') for h in header]
    columns: dict[tuple[str, int], list[int | None]] = {}
    for index, name in enumerate(header):
        match = _column(name)
        if match is None:
            raise InputError(
                path, f"column {name!r} is not <point>_cam<N>_X/Y", where="line 1", fix="give DLTdv's *xypts.csv"
            )
        axis = 0 if match["axis"] in "XUx" else 1
        columns.setdefault((match["point"], int(match["camera"])), [None, None])[axis] = index
    numbers = sorted({camera for _, camera in columns})
    if numbers != list(range(1, len(numbers) + 1)):
        raise InputError(path, f"its cameras are numbered {numbers}, not 1 to {len(numbers)}", where="line 1")
    pixels = _pixels(path, header, pixels)
    heights = _heights(path, videos, len(numbers), pixels)
    names = [video_name(v) for v in videos] or [f"cam{n}" for n in numbers]
    offsets = _offsets(path, len(numbers))
    found = []
    for (point, camera), (x_index, y_index) in columns.items():
        if x_index is None or y_index is None:
            raise InputError(path, f"point {point!r} camera {camera} lacks its x or y column", where="line 1")
        found.append((point, camera - 1, x_index, y_index))
    detections = []
    early = 0
    row = 0  # row 1 is camera 1's frame 1
    for number, fields in records:
        if not any(f.strip() for f in fields):
            continue
        if len(fields) != len(header):
            raise InputError(path, f"{len(fields)} values where the header has {len(header)}", where=f"line {number}")
        row += 1
        for point, camera, x_index, y_index in found:
            u, v = fields[x_index].strip(), fields[y_index].strip()
            if u.lower() == "nan" or v.lower() == "nan" or not u or not v:
                continue
            try:
                uv = float(u), float(v)
            except ValueError:
                raise InputError(path, f"{u!r}, {v!r} is not a position", where=f"line {number}") from None
            if not all(math.isfinite(c) for c in uv):
                continue
            frame = row + offsets[camera] - 1
            if frame < 0:
                early += 1
                continue
            x, y = pixels.to_opencv(np.array(uv[0]), np.array(uv[1]), heights[camera])
            detections.append(
                Detection(
                    video=names[camera],
                    frame=frame,
                    point=point,
                    x=float(x),
                    y=float(y),
                    score=None,
                    where=f"{path.name}:line {number}",
                )
            )
    if early:
        log.warning("%s: %d points fall before their video's first frame (its offset); left out", path, early)
    log.info("%s: %d cameras, %d points, pixels as %s's", path, len(numbers), len({p for p, *_ in found}), pixels.value)
    return detections


__all__ = ["is_dltdv_points", "read_dltdv_points"]
