"""DLTdv / easyWand / Argus files written from cameras we control, in each tool's pixel convention (the
conventions as docs/formats.md states them from the tools' source; written here independently of
tracking/pixels.py: the matrices below map OpenCV's pixels to the tool's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tracking.pixels import DltPixels


def opencv_to_tool(pixels: DltPixels, height: int) -> np.ndarray:
    """A (3, 3): the tool's (u, v, 1) = A (x, y, 1) for OpenCV's (x, y)."""
    return {
        DltPixels.DLTDV7: np.array([[1.0, 0, 1], [0, -1, height], [0, 0, 1]]),  # u = x + 1, v = H - y
        DltPixels.DLTDV8: np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 1]]),  # u = x + 1, v = y + 1
        DltPixels.ARGUS: np.array([[1.0, 0, 0], [0, -1, height], [0, 0, 1]]),  # u = x, v = H - y
        DltPixels.OPENCV: np.eye(3),
    }[pixels]


def coefficients(K: np.ndarray, R: np.ndarray, t: np.ndarray, pixels: DltPixels, height: int) -> np.ndarray:
    """L1..L11 (11,) of a camera cam_from_world R, t (world units) in the tool's pixels."""
    P = opencv_to_tool(pixels, height) @ K @ np.c_[R, t]
    P = P / P[2, 3]
    return np.r_[P[0], P[1], P[2, :3]]


def write_dlt_columns(path: Path, table: np.ndarray) -> Path:
    """DLTdv / easyWand / Argus layout: 11 rows, a column per camera, no header; table (N, 11)."""
    path.write_text("\n".join(",".join(f"{v:.12g}" for v in row) for row in table.T) + "\n", encoding="utf-8")
    return path


def tool_points(xy: np.ndarray, pixels: DltPixels, height: int) -> np.ndarray:
    """OpenCV's pixels (..., 2) in the tool's."""
    A = opencv_to_tool(pixels, height)
    return xy @ A[:2, :2].T + A[:2, 2]


def write_xypts(path: Path, uv: np.ndarray, names: list[str], *, style: str = "dltdv7") -> Path:
    """uv (F, P, C, 2) in the tool's pixels, NaN where not digitized. style: dltdv7 (pt_camN_X/Y), dltdv84
    (name_camN_U/V) or argus (name_cam_N_x/y, columns sorted by name as Argus writes them)."""
    F, P, C, _ = uv.shape
    columns = []
    for p in range(P):
        for c in range(C):
            for axis in range(2):
                if style == "argus":
                    name = f"{names[p]}_cam_{c + 1}_{'xy'[axis]}"
                elif style == "dltdv84":
                    name = f"{names[p]}_cam{c + 1}_{'UV'[axis]}"
                else:
                    name = f"{names[p]}_cam{c + 1}_{'XY'[axis]}"
                columns.append((name, uv[:, p, c, axis]))
    if style == "argus":
        columns.sort(key=lambda column: column[0])
    lines = [",".join(name for name, _ in columns)]
    lines += [",".join("NaN" if np.isnan(v[f]) else f"{v[f]:.6f}" for _, v in columns) for f in range(F)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
