"""The board hint: ArUco markers in view when registration has no tracks, against rendered videos we control."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from board_video import render_board, write_video

from sfm.board_hint import board_hint, markers_in_view
from tracking.charuco import CharucoBoard

BOARD = CharucoBoard(
    columns=4, rows=5, square_size=0.054, marker_size=0.0405, dictionary="DICT_4X4_1000", inverted=True
)


def test_markers_of_a_board_are_named_and_texture_is_not(tmp_path: Path) -> None:
    board_frames = render_board(
        BOARD, [np.array([[1.3, 0, 100 + 10 * i], [0, 1.3, 40], [0, 0, 1]]) for i in range(6)], (640, 480)
    )
    texture = np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8)
    board_video = write_video(tmp_path / "cam_a.avi", board_frames)
    texture_video = write_video(tmp_path / "cam_b.avi", [cv2.GaussianBlur(texture, (5, 5), 1.0)] * 6)
    found = markers_in_view([board_video, texture_video])
    assert list(found) == ["DICT_4X4_1000"] and found["DICT_4X4_1000"] == {"cam_a": list(range(10))}
    hint = board_hint([board_video, texture_video])
    assert hint is not None and "cam_a" in hint and "cam_b" not in hint and "ids 0-9" in hint and "--board" in hint
    assert board_hint([texture_video]) is None
    assert board_hint([tmp_path / "missing.mp4"]) is None  # a hint never fails the run
