"""Frame sources for the tracker: grayscale frames by 0-based decoded index.

`FrameSource` is the one thing the tracker needs: `len(source)` and `source.gray(i) -> (H, W) uint8`.
Implementations: `VideoFrames` (decodes a file), `ArrayFrames` (frames already in memory) and `CallableFrames`
(wraps someone else's cache, e.g. the labeling server's, through a `get(i) -> image` function).
"""

from __future__ import annotations

import logging
import zlib
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from dynrecon import video_io
from dynrecon.errors import InputError

log = logging.getLogger(__name__)


@runtime_checkable
class FrameSource(Protocol):
    """Random access to grayscale frames; frame i is the i-th decoded frame (0-based)."""

    def __len__(self) -> int: ...

    def gray(self, index: int) -> np.ndarray:
        """Frame `index` as (H, W) uint8."""
        ...


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3|4) BGR(A) -> (H, W) uint8."""
    if image.ndim == 2:
        gray = image
    elif image.ndim == 3 and image.shape[2] == 3:
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        gray = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    elif image.ndim == 3 and image.shape[2] == 1:
        gray = image[:, :, 0]
    else:
        raise ValueError(f"not an image: shape {image.shape}")
    if gray.dtype != np.uint8:
        gray = np.clip(gray, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(gray)


class ArrayFrames:
    """Frames held in memory: a sequence of (H, W) or (H, W, 3) BGR arrays, or one (F, H, W[, 3]) array."""

    def __init__(self, frames: Sequence[np.ndarray] | np.ndarray):
        self._frames = frames

    def __len__(self) -> int:
        return len(self._frames)

    def gray(self, index: int) -> np.ndarray:
        if not 0 <= index < len(self._frames):
            raise IndexError(f"frame {index} outside 0..{len(self._frames) - 1}")
        return to_gray(np.asarray(self._frames[index]))


class CallableFrames:
    """Adapter for a frame cache owned elsewhere: `get(i)` returns frame i as a gray or BGR array."""

    def __init__(self, num_frames: int, get: Callable[[int], np.ndarray]):
        self._num_frames = num_frames
        self._get = get

    def __len__(self) -> int:
        return self._num_frames

    def gray(self, index: int) -> np.ndarray:
        if not 0 <= index < self._num_frames:
            raise IndexError(f"frame {index} outside 0..{self._num_frames - 1}")
        return to_gray(self._get(index))


def _fingerprint(gray: np.ndarray) -> int:
    # A cheap checksum of a subsampled frame; it only has to tell neighbouring frames apart after a seek.
    return zlib.crc32(np.ascontiguousarray(gray[::7, ::7]).tobytes())


class VideoFrames:
    """Grayscale frames decoded from a video file (upright, through `dynrecon.video_io` like every reader), with
    an LRU cache of `cache_bytes`.

    Sequential reading is exact for every codec; seeking (`CAP_PROP_POS_FRAMES`) is not for all of them. So
    the file is read once from start to end at open (which also gives the exact frame count and a fingerprint
    of each frame). A later cache miss seeks to a little before the wanted frame, reads forward, and checks
    the fingerprint; when it does not match, it decodes from the start instead. Misses going backwards decode
    a whole block, so a backward sweep over a long video costs about one extra decode rather than a seek per
    frame.
    """

    def __init__(self, path: str | Path, *, cache_bytes: int = 1 << 30, block: int = 32):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(
                self.path, "video file not found", fix="check the path in videos.json or on the command line"
            )
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cache_bytes = cache_bytes
        self._bytes = 0
        self._block = max(1, block)
        self._cap: cv2.VideoCapture | None = None
        self._next = 0  # index of the frame the open capture returns on the next read()
        self._fingerprints: list[int] = []
        self._seek_ok = True
        self._scan()

    # -- public --
    def __len__(self) -> int:
        return len(self._fingerprints)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the frames."""
        return self._shape

    def gray(self, index: int) -> np.ndarray:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.path.name}: frame {index} outside 0..{len(self) - 1}")
        cached = self._cache.get(index)
        if cached is not None:
            self._cache.move_to_end(index)
            return cached
        if index < self._next or index - self._next > 2 * self._block:
            # Start a little early: the frames before `index` are the ones a backward sweep wants next.
            self._seek(max(0, index - self._block + 1))
        while self._next <= index:
            self._read_next()
        return self._cache[index]

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    # -- internals --
    def _open(self) -> cv2.VideoCapture:
        return video_io.open_video(self.path)

    def _scan(self) -> None:
        self._cap = self._open()
        self._next = 0
        times: list[float] = []
        while (frame := video_io.read(self._cap)) is not None:
            times.append(self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
            gray = to_gray(frame)
            self._fingerprints.append(_fingerprint(gray))
            self._shape = gray.shape[:2]
            self._store(self._next, gray)
            self._next += 1
        if not self._fingerprints:
            raise InputError(self.path, "no frame could be decoded", fix="convert it to H.264/HEVC/VP9 mp4")
        # Frames lost in the middle shift every later frame number: labels made on an intact copy land elsewhere.
        missing = video_io.missing_message(self.path, np.asarray(times), video_io.expected_frames(self._cap))
        if missing:
            log.warning("%s (labels are matched to the decoded frames' numbers)", missing)
        log.debug("%s: %d frames", self.path.name, len(self._fingerprints))

    def _store(self, index: int, gray: np.ndarray) -> None:
        self._cache[index] = gray
        self._cache.move_to_end(index)
        self._bytes += gray.nbytes
        while self._bytes > self._cache_bytes and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._bytes -= old.nbytes

    def _read_next(self) -> None:
        assert self._cap is not None  # _seek or _scan opened it
        frame = video_io.read(self._cap)
        if frame is None:
            raise InputError(
                self.path,
                f"frame {self._next} could not be decoded on a second read",
                fix="the file may have changed while tracking",
            )
        gray = to_gray(frame)
        if _fingerprint(gray) != self._fingerprints[self._next]:
            if self._seek_ok:
                log.info("%s: seeking is not exact for this codec; decoding sequentially", self.path.name)
                self._seek_ok = False
                target = self._next
                # Where the capture really is after the bad seek is unknown: start over from frame 0.
                self._cap.release()
                self._cap = self._open()
                self._next = 0
                self._seek(target)
                self._read_next()
                return
            raise InputError(
                self.path,
                f"frame {self._next} decodes differently on a second read",
                fix="the file may have changed while tracking",
            )
        if self._next not in self._cache:
            self._store(self._next, gray)
        self._next += 1

    def _seek(self, index: int) -> None:
        if self._cap is None:
            self._cap = self._open()
            self._next = 0
        if self._seek_ok and index > 0:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, index)
            self._next = index
            return
        if index < self._next:
            self._cap.release()
            self._cap = self._open()
            self._next = 0
        while self._next < index:
            if not video_io.grab(self._cap):
                raise InputError(self.path, f"frame {self._next} could not be decoded on a second read")
            self._next += 1
