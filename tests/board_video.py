"""Videos for the tests: a ChArUco board rendered through homographies, written losslessly."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from tracking.charuco import CharucoBoard

PPM = 1000.0  # the board is printed at this many pixels per metre


def render_board(board: CharucoBoard, homographies: Sequence[np.ndarray], size: tuple[int, int]) -> list[np.ndarray]:
    """BGR frames showing the board (printed at PPM px per metre, inverted when the board is) through each
    board-pixel -> image homography, on a grey background."""
    image = board.opencv().generateImage(
        (round(board.columns * board.square_size * PPM), round(board.rows * board.square_size * PPM))
    )
    if board.inverted:
        image = 255 - image
    frames = []
    for H in homographies:
        frame = cv2.warpPerspective(image, H, size, flags=cv2.INTER_AREA, borderValue=(160,))
        frames.append(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    return frames


def write_video(path: Path, frames: Sequence[np.ndarray], fps: float = 10.0) -> Path:
    """An FFV1 .avi of the frames (BGR, or gray converted), every pixel as given."""
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"FFV1"), fps, (width, height))
    for frame in frames:
        writer.write(frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path
