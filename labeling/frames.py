"""Single frames of a video as JPEG, decoded on demand with an LRU cache bounded in bytes."""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2

from dynrecon.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class VideoInfo:
    name: str
    path: Path
    frames: int
    width: int
    height: int
    fps: float


def probe_video(name: str, path: Path) -> VideoInfo:
    """Open a video once to learn its size; raises InputError when OpenCV cannot decode it."""
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise InputError(path, "OpenCV cannot open this video",
                             fix="use a format OpenCV decodes here (mp4 with H.264/HEVC/mp4v, avi MJPG, ...)")
        ok, frame = cap.read()
        if not ok or frame is None:
            raise InputError(path, "no frame could be decoded", fix="check the codec (AV1 is not supported)")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        height, width = frame.shape[:2]
    finally:
        cap.release()
    return VideoInfo(name=name, path=path, frames=max(count, 1), width=width, height=height, fps=fps)


class _Reader:
    """One VideoCapture per video; the next frame needs no seek, and scrubbing mostly asks for the next."""

    def __init__(self, info: VideoInfo):
        self.info = info
        self.lock = threading.Lock()
        self.cap: cv2.VideoCapture | None = None
        self.next_index = 0

    def read(self, index: int) -> cv2.typing.MatLike | None:
        with self.lock:
            if self.cap is None:
                self.cap = cv2.VideoCapture(str(self.info.path))
                self.next_index = 0
            # A short forward gap is cheaper to decode through than a seek to the previous keyframe.
            if not (self.next_index <= index <= self.next_index + 8):
                self.cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                self.next_index = index
            frame = None
            while self.next_index <= index:
                ok, frame = self.cap.read()
                if not ok:
                    self.cap.release()
                    self.cap = None
                    return None
                self.next_index += 1
            return frame

    def close(self) -> None:
        with self.lock:
            if self.cap is not None:
                self.cap.release()
                self.cap = None


class FrameCache:
    """JPEG bytes of (video, frame), least recently used first out once `max_bytes` is exceeded."""

    def __init__(self, videos: dict[str, VideoInfo], *, max_bytes: int = 256 << 20, jpeg_quality: int = 90):
        self.videos = videos
        self.max_bytes = max_bytes
        self.jpeg_quality = jpeg_quality
        self._readers = {name: _Reader(info) for name, info in videos.items()}
        self._cache: OrderedDict[tuple[str, int], bytes] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def cached_bytes(self) -> int:
        return self._bytes

    def jpeg(self, video: str, index: int) -> bytes | None:
        """JPEG of frame `index` (0-based decode order), or None when the video or frame does not exist."""
        reader = self._readers.get(video)
        if reader is None or index < 0 or index >= reader.info.frames:
            return None
        key = (video, index)
        with self._lock:
            data = self._cache.get(key)
            if data is not None:
                self._cache.move_to_end(key)
                self.hits += 1
                return data
        frame = reader.read(index)
        if frame is None:
            log.warning("%s: frame %d could not be decoded", reader.info.path, index)
            return None
        ok, encoded = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            return None
        data = encoded.tobytes()
        with self._lock:
            self.misses += 1
            if key not in self._cache:
                self._cache[key] = data
                self._bytes += len(data)
            while self._bytes > self.max_bytes and len(self._cache) > 1:
                _, dropped = self._cache.popitem(last=False)
                self._bytes -= len(dropped)
        return data

    def close(self) -> None:
        for reader in self._readers.values():
            reader.close()
