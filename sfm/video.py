"""Reading videos with OpenCV: probing frame count and per-frame timestamps, and decoding chosen frames.

Timestamps come from the decoder (`CAP_PROP_POS_MSEC` after each grab), not from the container's frame rate,
because phone videos often have a variable frame rate and the container's FPS/frame count are only nominal.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dynrecon.errors import InputError
from dynrecon.readers import check_video_name

log = logging.getLogger(__name__)

# Relative spread of frame intervals above which a video counts as variable-frame-rate (a recorded warning).
VFR_TOLERANCE = 0.05


@dataclass(kw_only=True)
class ProbedVideo:
    """What the decoder says about one video. `times`: (F,) seconds of each decoded frame from the first."""

    path: Path
    name: str
    width: int
    height: int
    times: np.ndarray
    nominal_fps: float | None

    @property
    def num_frames(self) -> int:
        return len(self.times)

    @property
    def fps(self) -> float | None:
        """The container's nominal frame rate, None when unknown or when the decoder's timestamps are irregular
        (the cameras.json contract; per-frame times carry the truth)."""
        return None if self.variable_frame_rate else self.nominal_fps

    @property
    def variable_frame_rate(self) -> bool:
        if self.num_frames < 3:
            return False
        steps = np.diff(self.times)
        return bool(np.ptp(steps) > VFR_TOLERANCE * max(float(np.median(steps)), 1e-9))


def video_name(path: Path) -> str:
    """The name a video goes by in every workspace file: its file name without extension, checked because it
    becomes a folder name (`frames/<video>/`)."""
    return check_video_name(path.stem, path)


def _open(path: Path) -> cv2.VideoCapture:
    if path.is_dir():
        raise InputError(path, "is a directory, not a video file", fix="give the video files themselves")
    if not path.exists():
        raise InputError(path, "file not found")
    if path.stat().st_size == 0:
        raise InputError(path, "file is empty (0 bytes)", fix="copy the video again")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InputError(
            path,
            "OpenCV cannot open this video",
            fix="convert it to H.264 MP4 (e.g. ffmpeg -i in -c:v libx264 out.mp4)",
        )
    return capture


def probe_video(path: str | Path) -> ProbedVideo:
    """Decode every frame header once to count frames and read their timestamps."""
    path = Path(path)
    video_name(path)  # before decoding the whole video, not after
    capture = _open(path)
    try:
        nominal = capture.get(cv2.CAP_PROP_FPS)
        times: list[float] = []
        width = height = 0
        while capture.grab():
            times.append(capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
            if not width:
                ok, image = capture.retrieve()
                if ok:
                    height, width = image.shape[:2]
    finally:
        capture.release()
    if not times or not width:
        raise InputError(
            path, "no decodable frames", fix="check the file plays; AV1 is not supported, convert to H.264"
        )
    stamps = np.asarray(times, dtype=float)
    if np.any(np.diff(stamps) <= 0):
        # Some containers report no timestamps (all 0): use the nominal rate rather than invent an order.
        if nominal and nominal > 0:
            log.warning("%s: decoder timestamps not increasing; using the nominal %.3f fps", path, nominal)
            stamps = np.arange(len(times)) / nominal
        else:
            raise InputError(
                path,
                "decoder timestamps are not increasing and the frame rate is unknown",
                fix="re-encode the video with a constant frame rate",
            )
    stamps = stamps - stamps[0]
    info = ProbedVideo(
        path=path,
        name=video_name(path),
        width=width,
        height=height,
        times=stamps,
        nominal_fps=float(nominal) if nominal and nominal > 0 else None,
    )
    if info.variable_frame_rate:
        log.warning(
            "%s: variable frame rate (intervals %.1f-%.1f ms); per-frame decoder timestamps are used",
            path,
            1000 * np.diff(stamps).min(),
            1000 * np.diff(stamps).max(),
        )
    return info


def read_frames(path: Path, frames: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame number, BGR image) for the decoded frame numbers `frames`, in increasing order."""
    wanted = sorted(int(f) for f in frames)
    capture = _open(path)
    try:
        index = -1
        for target in wanted:
            while index < target:
                if not capture.grab():
                    raise InputError(path, f"frame {target} cannot be decoded", fix="the video may be truncated")
                index += 1
            ok, image = capture.retrieve()
            if not ok:
                raise InputError(path, f"frame {target} cannot be decoded", fix="the video may be truncated")
            yield target, image
    finally:
        capture.release()
