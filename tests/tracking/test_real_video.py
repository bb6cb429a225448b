"""Real phone-camera footage (pose2sim demo, static cameras): background corners must stay where they are."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tracking.frames import VideoFrames
from tracking.options import TrackOptions
from tracking.propagate import track_video
from tracking.steps import ncc, patch_at


@pytest.mark.shared
def test_static_background_points_do_not_move_on_real_video(shared_dir: Path) -> None:
    # cam03: a person moves next to some of the corners, which once dragged tracks up to 37 px away (caught by
    # the closure check against the next label).
    frames = VideoFrames(shared_dir / "data" / "videos" / "pose2sim_demo" / "videos" / "cam03.mp4")
    first = frames.gray(0)
    corners = cv2.goodFeaturesToTrack(first, 80, 0.03, 50).reshape(-1, 2)
    # Truly static corners: the patch there looks the same all through the video (the person never covers it).
    static = [
        c
        for c in corners
        if min(ncc(patch_at(frames.gray(f), c, 21), patch_at(first, c, 21)) for f in range(0, len(frames), 3)) > 0.95
    ]
    assert len(static) >= 20
    labels = {f"c{i}": {f: (float(c[0]), float(c[1])) for f in range(0, len(frames), 10)} for i, c in enumerate(static)}
    result = track_video(frames, labels, TrackOptions())
    errors = np.array(
        [np.hypot(p.x - c[0], p.y - c[1]) for i, c in enumerate(static) for f, p in result[f"c{i}"].items() if f % 10]
    )
    assert len(errors) > 0.9 * len(static) * 90
    assert np.median(errors) < 0.05
    assert errors.max() < 3.0
