"""Pixel conventions of the tools whose 2D points and DLT coefficients dynrecon imports (DLTdv, easyWand, Argus),
against OpenCV's (x right, y down, the top-left pixel's centre at (0, 0)); H is the image height.

From the tools' source (docs/formats.md, "DLTdv, easyWand and Argus"): DLTdv 5-7 (and easyWand fed from it) draw
the frame flipped upside down in MATLAB's 1-based pixels: u = x + 1, v = H - y; Argus counts rows up from the
bottom too but columns from 0: u = x, v = H - y; DLTdv 8 uses MATLAB's pixels as they are: u = x + 1, v = y + 1.
"""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the command line's option parsers import this module: numpy is not loaded for --help
    import numpy as np


class DltPixels(enum.Enum):
    """The pixel convention of a DLT file or of DLTdv / Argus 2D points (see the module doc)."""

    AUTO = "auto"
    DLTDV7 = "dltdv7"  # DLTdv 5-7, easyWand fed from it: 1-based columns, rows up from the bottom
    DLTDV8 = "dltdv8"  # DLTdv 8: MATLAB's 1-based pixels, rows down from the top
    ARGUS = "argus"  # Argus: 0-based columns, rows up from the bottom
    OPENCV = "opencv"  # 0-based, rows down from the top (OpenCV, OpenPose, DeepLabCut)

    @property
    def from_bottom(self) -> bool:
        return self in (DltPixels.DLTDV7, DltPixels.ARGUS)

    @property
    def column_origin(self) -> float:
        """The file's column of OpenCV's pixel x = 0."""
        return 1.0 if self in (DltPixels.DLTDV7, DltPixels.DLTDV8) else 0.0

    def to_opencv(self, u: np.ndarray, v: np.ndarray, height: int | None) -> tuple[np.ndarray, np.ndarray]:
        """The file's (u, v) as OpenCV's (x, y); `height` (the video's) is needed for bottom-up rows."""
        x = u - self.column_origin
        if self.from_bottom:
            if height is None:
                raise ValueError("bottom-up rows need the image height")
            return x, height - v
        return x, v - (1.0 if self is DltPixels.DLTDV8 else 0.0)


__all__ = ["DltPixels"]
