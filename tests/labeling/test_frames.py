"""Frames on demand: same pixels in any access order, unknown frames are None, LRU eviction by bytes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from labeling_videos import FRAMES

from labeling.frames import FrameCache, probe_video


def decode(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).astype(float)


def test_random_access_matches_sequential(video: Path) -> None:
    info = probe_video("cam1", video)
    assert (info.frames, info.width, info.height) == (FRAMES, 320, 240)
    sequential = FrameCache({"cam1": info}, jpeg_quality=95)
    expected = [decode(sequential.jpeg("cam1", i) or b"") for i in range(FRAMES)]
    shuffled = FrameCache({"cam1": info}, jpeg_quality=95, max_bytes=1)
    order = np.random.default_rng(3).permutation(FRAMES)
    for i in order:
        got = decode(shuffled.jpeg("cam1", int(i)) or b"")
        assert np.abs(got - expected[i]).mean() < 1.0, i
    assert shuffled.jpeg("cam1", FRAMES) is None
    assert shuffled.jpeg("cam1", -1) is None
    assert shuffled.jpeg("other", 0) is None
    sequential.close()
    shuffled.close()


def test_lru_keeps_the_recently_used(video: Path) -> None:
    info = probe_video("cam1", video)
    cache = FrameCache({"cam1": info})
    size = len(cache.jpeg("cam1", 0) or b"")
    cache.max_bytes = int(3.5 * size)
    for i in (1, 2):
        cache.jpeg("cam1", i)
    cache.jpeg("cam1", 0)  # touch 0: now 1 is the oldest
    cache.jpeg("cam1", 3)
    assert set(cache._cache) == {("cam1", 2), ("cam1", 0), ("cam1", 3)}
    assert cache.cached_bytes <= cache.max_bytes
    cache.close()


_VideoCapture = cv2.VideoCapture


class _SloppySeek:
    """A VideoCapture whose seeks land one frame early, like some codecs' inexact seeking."""

    def __init__(self, path: str):
        self._cap = _VideoCapture(path)

    def set(self, prop: int, value: float) -> bool:
        if prop == cv2.CAP_PROP_POS_FRAMES:
            value = max(0, value - 1)
        return self._cap.set(prop, value)

    def __getattr__(self, name: str) -> object:
        return getattr(self._cap, name)


def test_inexact_seeking_is_detected_and_bypassed(video: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    info = probe_video("cam1", video)
    honest = FrameCache({"cam1": info}, jpeg_quality=95)
    expected = decode(honest.jpeg("cam1", 15) or b"")
    expected_3 = decode(honest.jpeg("cam1", 3) or b"")
    honest.close()
    from labeling import frames as frames_module

    monkeypatch.setattr(frames_module.cv2, "VideoCapture", _SloppySeek)
    cache = FrameCache({"cam1": info}, jpeg_quality=95)
    assert cache.wait_scanned(30) and cache.frame_count("cam1") == FRAMES
    got = decode(cache.jpeg("cam1", 15) or b"")
    assert np.abs(got - expected).mean() < 1.0
    assert not cache._readers["cam1"].seek_ok
    # Backwards, now without seeking: reopen and decode forward.
    assert np.abs(decode(cache.jpeg("cam1", 3) or b"") - expected_3).mean() < 1.0
    cache.close()
