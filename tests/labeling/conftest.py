"""Fixtures of the labeling tests: a small synthetic video (see labeling_videos.py) and a workspace."""

from __future__ import annotations

from pathlib import Path

import pytest
from labeling_videos import write_video


@pytest.fixture
def video(tmp_path: Path) -> Path:
    return write_video(tmp_path / "cam1.avi")


@pytest.fixture
def workspace(tmp_path: Path) -> Path:
    ws = tmp_path / "ws"
    ws.mkdir()
    return ws
