"""One imported 2D detection, before point renaming and the confidence threshold."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class Detection:
    video: str
    frame: int  # 0-based decoded frame index
    point: str
    x: float  # pixels, OpenCV convention (top-left pixel centre is (0, 0))
    y: float
    score: float | None  # the detector's confidence; None when the format has none
    where: str  # file and line (or file) it came from, for messages
