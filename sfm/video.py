"""Reading videos with OpenCV: probing frame count and per-frame timestamps, and decoding chosen frames.

Timestamps come from the decoder (`CAP_PROP_POS_MSEC` after each grab), not from the container's frame rate,
because phone videos often have a variable frame rate and the container's FPS/frame count are only nominal.
Opening, orientation (upright) and skipping damaged packets are `dynrecon.video_io`'s, shared by every reader.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dynrecon import video_io
from dynrecon.errors import InputError
from dynrecon.readers import check_video_name

log = logging.getLogger(__name__)

# Relative spread of frame intervals above which a video counts as variable-frame-rate (a recorded warning).
VFR_TOLERANCE = 0.05
TIME_BASE_S = 0.001 + 1e-9  # the coarsest container time base of constant-rate videos (Matroska's millisecond)
RATE_TOLERANCE = 0.05  # the nominal rate is kept when the decoder's median step is 1 / rate within this share


@dataclass(kw_only=True)
class ProbedVideo:
    """What the decoder says about one video. `times`: (F,) seconds of each decoded frame from the first;
    `width`, `height`: of the upright frames, after the container's rotation flag (`rotation` degrees)."""

    path: Path
    name: str
    width: int
    height: int
    times: np.ndarray
    nominal_fps: float | None
    rotation: int = 0
    expected_frames: int | None = None  # the container's frame count; more than num_frames when frames are lost
    missing: str | None = None  # the one-line warning saying how many frames are missing and where
    stand_in: bool = False  # not here: its frames and times from the tracks and --fps, no pixels

    @property
    def num_frames(self) -> int:
        return len(self.times)

    @property
    def fps(self) -> float | None:
        """The container's nominal frame rate, None when unknown, when the decoder's timestamps are irregular or
        when their step is not 1 / the rate (the cameras.json contract; per-frame times carry the truth)."""
        if self.variable_frame_rate or not self.nominal_fps:
            return None
        # containers report garbage rates (1000 for browser WebM, 90000 for IP cameras)
        if self.num_frames >= 3 and abs(self.median_step * self.nominal_fps - 1.0) > RATE_TOLERANCE:
            return None
        return self.nominal_fps

    @property
    def span(self) -> tuple[float, float]:
        """The video's own time span: its first and last decoded frame's time (s)."""
        return float(self.times[0]), float(self.times[-1])

    @property
    def frame_period(self) -> float:
        """Seconds per frame: 1 / `fps`, else the decoder's median step (inf for one frame)."""
        return 1.0 / self.fps if self.fps else self.median_step

    @property
    def median_step(self) -> float:
        """The median step between the decoder's timestamps (s); inf for one frame."""
        return float(np.median(np.diff(self.times))) if self.num_frames > 1 else math.inf

    @property
    def variable_frame_rate(self) -> bool:
        if self.num_frames < 3:
            return False
        if np.ptp(np.diff(self.times)) <= VFR_TOLERANCE * max(self.median_step, 1e-9):
            return False
        # Matroska / WebM store times in milliseconds: a constant rate's frames then sit within a time base of an
        # even grid (16 and 17 ms steps at 60 fps), where a dropped frame moves them by a whole period
        grid = np.linspace(self.times[0], self.times[-1], self.num_frames)
        return bool(np.max(np.abs(self.times - grid)) > min(TIME_BASE_S, 0.25 * self.median_step))


def video_name(path: Path) -> str:
    """The name a video goes by in every workspace file: its file name without extension, checked because it
    becomes a folder name (`frames/<video>/`)."""
    return check_video_name(path.stem, path)


def probe_video(path: str | Path) -> ProbedVideo:
    """Decode every frame once to count frames and read their timestamps; warns when frames are missing."""
    path = Path(path)
    name = video_name(path)  # before decoding the whole video, not after
    capture = video_io.open_video(path)
    try:
        nominal = capture.get(cv2.CAP_PROP_FPS)
        expected = video_io.expected_frames(capture)
        times, (height, width) = _decode_times(capture, path)
        rotation = video_io.rotation(capture)
    finally:
        capture.release()
    missing = video_io.missing_message(path, times, expected)
    if missing:
        log.warning("%s", missing)
    info = ProbedVideo(
        path=path,
        name=name,
        width=width,
        height=height,
        times=_increasing(times, nominal, path),
        nominal_fps=float(nominal) if nominal and nominal > 0 else None,
        rotation=rotation,
        expected_frames=expected,
        missing=missing,
    )
    if info.variable_frame_rate and not missing:  # missing frames make the steps uneven; that warning says so
        steps = np.diff(info.times)
        log.warning(
            "%s: variable frame rate (intervals %.1f-%.1f ms); per-frame decoder timestamps are used",
            path,
            1000 * steps.min(),
            1000 * steps.max(),
        )
    return info


def _decode_times(capture: cv2.VideoCapture, path: Path) -> tuple[np.ndarray, tuple[int, int]]:
    """(F,) decoder timestamps in seconds, and the (height, width) of the first frame."""
    times: list[float] = []
    shape = (0, 0)
    while video_io.grab(capture):
        times.append(capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
        if not shape[0]:
            ok, image = capture.retrieve()
            shape = image.shape[:2] if ok else shape
    if not times or not shape[0]:
        raise InputError(
            path, "no decodable frames", fix="check the file plays; AV1 is not supported, convert to H.264"
        )
    return np.asarray(times, dtype=float), (int(shape[0]), int(shape[1]))


def _increasing(stamps: np.ndarray, nominal: float, path: Path) -> np.ndarray:
    """The timestamps from the first frame, or the nominal rate's when the decoder's do not increase."""
    if np.any(np.diff(stamps) <= 0):
        # Some containers report no timestamps (all 0): use the nominal rate rather than invent an order.
        if not (nominal and nominal > 0):
            raise InputError(
                path,
                "decoder timestamps are not increasing and the frame rate is unknown",
                fix="re-encode the video with a constant frame rate",
            )
        log.warning("%s: decoder timestamps not increasing; using the nominal %.3f fps", path, nominal)
        return np.arange(len(stamps)) / nominal
    return stamps - stamps[0]


def read_frames(path: Path, frames: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame number, BGR image) for the decoded frame numbers `frames`, in increasing order."""
    wanted = sorted(int(f) for f in frames)
    capture = video_io.open_video(path)
    try:
        index = -1
        for target in wanted:
            while index < target:
                if not video_io.grab(capture):
                    raise InputError(path, f"frame {target} cannot be decoded", fix="the video may be truncated")
                index += 1
            ok, image = capture.retrieve()
            if not ok:
                raise InputError(path, f"frame {target} cannot be decoded", fix="the video may be truncated")
            yield target, image
    finally:
        capture.release()
