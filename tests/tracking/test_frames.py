from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.errors import InputError
from tracking.frames import ArrayFrames, CallableFrames, FrameSource, VideoFrames, to_gray
from tracking.synthetic import SyntheticVideo


def test_video_frames_match_the_written_frames_in_any_order(small_video: SyntheticVideo) -> None:
    assert small_video.path is not None and small_video.frames is not None
    # A tiny cache forces re-decoding: backward sweeps, jumps and forward reads must all return the right
    # frame.
    frames = VideoFrames(small_video.path, cache_bytes=5 * 320 * 240, block=4)
    assert len(frames) == len(small_video.frames) == 40
    assert frames.shape == (240, 320)
    order = [*range(39, -1, -1), 3, 30, 2, 17, 17, 0, 39]
    for index in order:
        expected = to_gray(small_video.frames[index])  # FFV1 is lossless
        np.testing.assert_array_equal(frames.gray(index), expected, err_msg=f"frame {index}")
    with pytest.raises(IndexError):
        frames.gray(40)
    frames.close()


def test_inexact_seek_falls_back_to_sequential_decoding(small_video: SyntheticVideo) -> None:
    assert small_video.path is not None and small_video.frames is not None
    frames = VideoFrames(small_video.path, cache_bytes=2 * 320 * 240, block=2)
    real_seek = cv2.VideoCapture.set

    class LyingCapture:
        """A capture whose seek lands two frames early, like some codecs' keyframe seeks."""

        def __init__(self, path: str):
            self.cap = cv2.VideoCapture(path)

        def set(self, prop: int, value: float) -> bool:
            assert prop == cv2.CAP_PROP_POS_FRAMES
            return real_seek(self.cap, prop, max(0, value - 2))

        def __getattr__(self, name: str) -> object:
            return getattr(self.cap, name)

    frames._cap = LyingCapture(str(small_video.path))  # type: ignore[assignment]
    frames._next = 40
    frames._open = lambda: LyingCapture(str(small_video.path))  # type: ignore[method-assign]
    for index in (30, 10, 25):
        np.testing.assert_array_equal(frames.gray(index), to_gray(small_video.frames[index]))
    assert not frames._seek_ok


def test_missing_and_undecodable_videos_are_input_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        VideoFrames(tmp_path / "nope.mp4")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all" * 10)
    with pytest.raises(InputError, match=r"junk\.mp4"):
        VideoFrames(junk)


def test_array_and_callable_sources() -> None:
    bgr = np.zeros((3, 8, 10, 3), np.uint8)
    bgr[1, :, :, 1] = 200
    arrays = ArrayFrames(bgr)
    wrapped = CallableFrames(3, lambda i: bgr[i])
    for source in (arrays, wrapped):
        assert isinstance(source, FrameSource)
        assert len(source) == 3
        gray = source.gray(1)
        assert gray.shape == (8, 10) and gray.dtype == np.uint8
        assert gray[0, 0] == round(0.587 * 200)
        with pytest.raises(IndexError):
            source.gray(3)
