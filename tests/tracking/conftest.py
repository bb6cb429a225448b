"""A small rendered video shared by the tracking tests (rendering is the slow part)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tracking.synthetic import SyntheticOptions, SyntheticVideo, render_video

SMALL = SyntheticOptions(
    width=320,
    height=240,
    frames=40,
    markers=5,
    marker_radius=9.0,
    speed=3.0,
    pan=1.5,
    blur_samples=3,
    exposure=0.6,
    fourcc="FFV1",
    seed=7,
)


@pytest.fixture(scope="session")
def small_video(tmp_path_factory: pytest.TempPathFactory) -> SyntheticVideo:
    """(40 frames, 320x240, 5 markers, occluder, FFV1) with ground truth; frames kept in memory too."""
    path: Path = tmp_path_factory.mktemp("synthetic") / "cam0.avi"
    return render_video(path, SMALL, keep_frames=True)
