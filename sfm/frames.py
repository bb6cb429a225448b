"""Choosing which decoded frames go to SfM, and writing them (resized) into the workspace.

Frame numbers always refer to the original decoded frame index; the image of frame n of video v is
`frames/<v>/<n:06d>.jpg`, resized so that its long side is at most `long_side` pixels.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from dynrecon.readers import check_video_name
from sfm.video import ProbedVideo, read_frames

JPEG_QUALITY = 95


def sfm_folder(video: str) -> str:
    """The video's folder in frames/ and masks/ (and its COLMAP image names): the name with `%` and whitespace
    percent-encoded, since COLMAP's pair lists split image names at spaces."""
    return "".join(f"%{ord(c):02X}" if c == "%" or c.isspace() else c for c in video)


def image_name(video: str, frame: int) -> str:
    """COLMAP image name (relative to the frames folder) of a decoded frame."""
    return f"{sfm_folder(video)}/{frame:06d}.jpg"


def select_frames(
    info: ProbedVideo, *, step: int = 0, time_step: float | None = None, max_frames: int = 40
) -> np.ndarray:
    """Sorted frame numbers for SfM: every `step`-th frame, or one per `time_step` seconds (by decoder
    timestamps), or all; then thinned evenly to at most `max_frames` (first and last kept)."""
    count = info.num_frames
    if time_step:
        targets = np.arange(0.0, info.times[-1] + 1e-9, time_step)
        frames = np.unique(np.abs(info.times[None, :] - targets[:, None]).argmin(axis=1))
    elif step > 0:
        frames = np.arange(0, count, step)
    else:
        frames = np.arange(count)
    if max_frames > 0 and len(frames) > max_frames:
        frames = frames[np.unique(np.round(np.linspace(0, len(frames) - 1, max_frames)).astype(int))]
    return frames.astype(np.int64)


@dataclass(kw_only=True)
class Resize:
    """Scale from original to SfM pixels. Pixel centres map as x_small = (x + 0.5) * scale - 0.5."""

    scale: float
    width: int
    height: int

    @classmethod
    def for_video(cls, info: ProbedVideo, long_side: int) -> Resize:
        return cls.for_video_size(info.width, info.height, long_side)

    @classmethod
    def for_video_size(cls, width: int, height: int, long_side: int) -> Resize:
        longest = max(width, height)
        scale = min(1.0, long_side / longest) if long_side > 0 else 1.0
        return cls(scale=scale, width=max(1, round(width * scale)), height=max(1, round(height * scale)))

    def to_small(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy, dtype=float) + 0.5) * self.scale - 0.5


def write_frames(
    info: ProbedVideo, frames: np.ndarray, frames_dir: Path, resize: Resize, desc: str = "decoding frames"
) -> list[str]:
    """Decode `frames` and write them (resized) as JPEG; returns their image names.

    Files of an earlier run are reused only when they come from the same video file at the same size (a
    `.source` stamp in the folder says which); otherwise the folder is emptied first."""
    names = []
    folder = frames_dir / sfm_folder(check_video_name(info.name, info.path))  # the folder may be emptied: never `..`
    stat = info.path.stat()
    stamp = f"{info.path.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{resize.width}x{resize.height}\n"
    marker = folder / ".source"
    if folder.exists() and (not marker.exists() or marker.read_text(encoding="utf-8") != stamp):
        shutil.rmtree(folder)
    folder.mkdir(parents=True, exist_ok=True)
    marker.write_text(stamp, encoding="utf-8")
    missing = [int(f) for f in frames if not (frames_dir / image_name(info.name, int(f))).exists()]
    for frame, image in tqdm(
        read_frames(info.path, np.asarray(missing)),
        total=len(missing),
        desc=f"{desc} {info.name}",
        unit="frame",
        leave=False,
    ):
        if resize.scale != 1.0:
            image = cv2.resize(image, (resize.width, resize.height), interpolation=cv2.INTER_AREA)
        path = frames_dir / image_name(info.name, frame)
        tmp = path.with_name(f".{path.name}.tmp.jpg")
        cv2.imwrite(str(tmp), image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        tmp.replace(path)
    for frame in frames:
        names.append(image_name(info.name, int(frame)))
    return names
