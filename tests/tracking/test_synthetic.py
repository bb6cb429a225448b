from __future__ import annotations

from pathlib import Path

import numpy as np

from tracking.accuracy import labels_every, score
from tracking.frames import ArrayFrames, VideoFrames
from tracking.options import TrackOptions
from tracking.propagate import track_video
from tracking.synthetic import SyntheticOptions, render_video


def test_ground_truth_matches_the_pictures_without_blur_or_noise(tmp_path: Path) -> None:
    # With a sharp, noise-free, lossless video, one LK step from a true position must land on the ground truth
    # to a small fraction of a pixel; an offset in the renderer's conventions (e.g. half a pixel) would show.
    options = SyntheticOptions(
        width=240, height=180, frames=12, markers=3, blur_samples=1, noise=0.0, occluder=False, seed=3
    )
    video = render_video(tmp_path / "sharp.avi", options)
    frames = VideoFrames(tmp_path / "sharp.avi")
    assert len(frames) == 12 and frames.shape == (180, 240)
    accuracy = score(track_video(frames, labels_every(video, 2), TrackOptions()), video)
    assert accuracy.coverage == 1.0
    assert accuracy.median < 0.05 and float(accuracy.errors.max()) < 0.15
    assert video.visible.all()


def test_occluder_hides_markers_and_motion_is_as_asked() -> None:
    options = SyntheticOptions(width=200, height=160, frames=24, markers=6, blur_samples=2, speed=4.0, seed=5)
    video = render_video(None, options)
    assert video.frames is not None and len(video.frames) == 24 and video.frames[0].shape == (160, 200, 3)
    assert video.uv.shape == (24, 6, 2) and video.visible.shape == (24, 6)
    hidden = ~video.visible
    # The bar crosses during the middle half only.
    assert hidden[6:18].any() and not hidden[:5].any() and not hidden[19:].any()
    steps = np.linalg.norm(np.diff(video.uv, axis=0), axis=2)
    assert 1.0 < np.median(steps) < 12.0
    # Same seed, same video.
    again = render_video(None, options)
    assert again.frames is not None
    np.testing.assert_array_equal(video.frames[7], again.frames[7])
    # Labels on hidden frames are "not visible" marks.
    labels = labels_every(video, 3)
    assert any(xy is None for marks in labels.values() for xy in marks.values())
    assert track_video(ArrayFrames(video.frames), labels, TrackOptions())  # runs on hidden marks
