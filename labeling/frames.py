"""Single frames of a video as JPEG, decoded on demand with an LRU cache bounded in bytes."""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dynrecon import video_io
from dynrecon.errors import InputError

log = logging.getLogger(__name__)

BACK_BLOCK = 8  # frames decoded and cached together when a request goes backwards


@dataclass(frozen=True, kw_only=True)
class VideoInfo:
    name: str
    path: Path
    frames: int
    width: int
    height: int
    fps: float


def probe_video(name: str, path: Path) -> VideoInfo:
    """Open a video once to learn its (upright) size; raises InputError when OpenCV cannot decode it."""
    cap = video_io.open_video(path)
    try:
        frame = video_io.read(cap)
        if frame is None:
            raise InputError(path, "no frame could be decoded", fix="check the codec (AV1 is not supported)")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        height, width = frame.shape[:2]
    finally:
        cap.release()
    return VideoInfo(name=name, path=path, frames=max(count, 1), width=width, height=height, fps=fps)


def fingerprint(image: np.ndarray) -> int:
    """Cheap checksum of a subsampled frame: tells a frame from its neighbours after a seek."""
    return zlib.crc32(np.ascontiguousarray(image[::7, ::7]).tobytes())


class _Reader:
    """One VideoCapture per video; the next frame needs no seek, and scrubbing mostly asks for the next.

    Seeking (`CAP_PROP_POS_FRAMES`) is not exact for every codec, and a label on the wrong frame would be
    silently wrong. So a background scan decodes the video once, sequentially, recording each frame's
    fingerprint and the exact frame count; a seek whose frame does not match the scan switches this video to
    sequential decoding (slower, always right).
    """

    def __init__(self, info: VideoInfo):
        self.info = info
        self.lock = threading.Lock()
        self.cap: cv2.VideoCapture | None = None
        self.next_index = 0
        self.fingerprints: list[int] = []  # filled by the scan, in order
        self.scanned = False  # True once `fingerprints` covers the whole video
        self.seek_ok = True

    @property
    def frames(self) -> int:
        return len(self.fingerprints) if self.scanned else self.info.frames

    def read(self, index: int) -> np.ndarray | None:
        with self.lock:
            frame = self._read(index)
            if (
                frame is not None
                and index < len(self.fingerprints)
                and fingerprint(frame) != self.fingerprints[index]
                and self.seek_ok
            ):
                log.warning("%s: seeking is not exact for this video; decoding sequentially", self.info.path)
                self.seek_ok = False
                self._close()
                frame = self._read(index)
            return frame

    def _read(self, index: int) -> np.ndarray | None:
        if self.cap is None:
            try:
                self.cap = video_io.open_video(self.info.path)
            except InputError as error:
                log.warning("%s", error)  # the file went away after startup: no frame, not a server error
                return None
            self.next_index = 0
        # A short forward gap is cheaper to decode through than a seek to the previous keyframe.
        if not (self.next_index <= index <= self.next_index + 8):
            if self.seek_ok:
                self.cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                self.next_index = index
            elif index < self.next_index:
                self._close()
                return self._read(index)
        while self.next_index < index:
            if not video_io.grab(self.cap):
                self._close()
                return None
            self.next_index += 1
        frame = video_io.read(self.cap)
        if frame is None:
            self._close()
            return None
        self.next_index += 1
        return frame

    def _close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None

    def scan(self, stop: threading.Event) -> None:
        try:
            cap = video_io.open_video(self.info.path)
        except InputError as error:
            # The file went away or changed after startup: keep the container's count, the page still runs.
            log.warning("%s", error)
            return
        try:
            while not stop.is_set() and (frame := video_io.read(cap)) is not None:
                self.fingerprints.append(fingerprint(frame))
        finally:
            cap.release()
        if not stop.is_set():
            self.scanned = True
            missing = video_io.count_message(self.info.path, len(self.fingerprints), self.info.frames)
            if missing:
                log.warning("%s", missing)

    def close(self) -> None:
        with self.lock:
            self._close()


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
        self._stop = threading.Event()
        self._scanner = threading.Thread(target=self._scan_all, name="frame-scan", daemon=True)
        self._scanner.start()

    def _scan_all(self) -> None:
        # Background work: on Linux a thread has its own nice value, so the scan yields the CPU to frames
        # the user is waiting for and to tracking.
        with contextlib.suppress(AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
        for reader in self._readers.values():
            reader.scan(self._stop)

    def frame_count(self, video: str) -> int:
        """Exact once the background scan has finished that video, the container's count before."""
        return self._readers[video].frames

    def wait_scanned(self, timeout: float | None = None) -> bool:
        self._scanner.join(timeout)
        return not self._scanner.is_alive()

    @property
    def cached_bytes(self) -> int:
        return self._bytes

    def jpeg(self, video: str, index: int) -> bytes | None:
        """JPEG of frame `index` (0-based decode order), or None when the video or frame does not exist."""
        reader = self._readers.get(video)
        if reader is None or index < 0 or index >= reader.frames:
            return None
        key = (video, index)
        with self._lock:
            data = self._cache.get(key)
            if data is not None:
                self._cache.move_to_end(key)
                self.hits += 1
                return data
        with self._lock:
            self.misses += 1
        start = index
        if index < reader.next_index:
            # Going backwards costs a seek to the previous keyframe and a decode forward from there; keep the
            # frames decoded on the way, which are the ones someone stepping backwards asks for next.
            start = max(0, index - BACK_BLOCK + 1)
        data = None
        for i in range(start, index + 1):
            frame = reader.read(i)
            if frame is None:
                log.warning("%s: frame %d could not be decoded", reader.info.path, i)
                return None
            with self._lock:
                cached = self._cache.get((video, i)) if i != index else None
            data = cached if cached is not None else self._store((video, i), frame)
        return data

    def _store(self, key: tuple[str, int], frame: np.ndarray) -> bytes | None:
        ok, encoded = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            return None
        data = encoded.tobytes()
        with self._lock:
            if key not in self._cache:
                self._cache[key] = data
                self._bytes += len(data)
            self._cache.move_to_end(key)
            while self._bytes > self.max_bytes and len(self._cache) > 1:
                _, dropped = self._cache.popitem(last=False)
                self._bytes -= len(dropped)
        return data

    def close(self) -> None:
        self._stop.set()
        self._scanner.join()
        for reader in self._readers.values():
            reader.close()
