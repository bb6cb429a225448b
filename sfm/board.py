"""A known calibration board seen in the subject's tracks (`register --board`): each camera's intrinsics, and the
metric scale.

A ChArUco board's inner corners (`corner_<id>` points, from `dynrecon import-tracks VIDEO... --board FILE`) have
known positions on a plane. Each frame that sees enough of them is one view of Zhang's calibration
(`cv2.calibrateCamera`): a camera's focal length, principal point and radial distortion come from its own views
alone, so no synchronization is needed. The subject path then poses the cameras and finds their clock offsets with
these intrinsics held, and the board's known corner spacing gives the metric scale.

A camera's board intrinsics are used only where its views determine them (enough views, small reprojection error,
small standard deviations of the focal length and principal point); otherwise the report says why, and the
subject path self-calibrates that camera as without a board.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from dynrecon.jsonvalues import finite_or_none
from tracking.charuco import CharucoBoard, board_corner_positions
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

MIN_CORNERS = 6  # corners a frame needs to be a view
MIN_VIEWS = 10  # views a camera needs
MAX_VIEWS = 80  # evenly spaced views kept at most (the fit's cost grows with them)
MAX_RMS_PX = 1.5  # reprojection rms of the board fit
MAX_FOCAL_STD = 0.03  # standard deviation of the focal length / focal length
# standard deviation of the principal point / long side: real principal points lie within a few % of the image
# centre, which the subject path holds where it has no intrinsics; a less certain estimate is no better than that
MAX_PP_STD = 0.015
# A view whose rms exceeds this x the median and MAX_RMS_PX (a misread corner id, not an oblique view) is left out
# and the fit redone once.
OUTLIER_VIEW = 3.0
# The board's orientations must differ by this much (largest angle between two views' board normals): views of
# one orientation leave the focal length and the distance to the board interchangeable (Zhang's degeneracy), and
# the fit's standard deviations do not show it.
MIN_TILT_SPREAD_DEG = 20.0
SCALE_FRAMES = 20  # frames in which a video must see both corners of the scale pair
# Zhang's model here: one focal (square pixels), free principal point, k1 and k2 (phones' and webcams' lenses);
# tangential terms and k3 are left out: a moving board in one capture does not determine them.
FLAGS = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3


@dataclass(kw_only=True)
class BoardIntrinsics:
    """One camera's intrinsics from its board views; `used` False (with `why`) when they are not determined."""

    name: str
    views: int
    used: bool
    why: str | None = None
    K: np.ndarray | None = None  # (3, 3)
    dist: np.ndarray | None = None  # (5,) OpenCV k1, k2, p1, p2, k3
    rms_px: float | None = None
    focal_std_pct: float | None = None
    pp_std_px: float | None = None
    tilt_spread_deg: float | None = None

    @property
    def fits(self) -> bool:
        """Whether the board's geometry explains this video's corners (whatever the intrinsics' precision)."""
        return self.rms_px is not None and self.rms_px <= MAX_RMS_PX

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "views": self.views, "used": self.used, "why": self.why}
        if self.K is not None and self.dist is not None:
            out.update(
                focal_px=round(float(self.K[0, 0]), 2),
                principal_point_px=[round(float(self.K[0, 2]), 2), round(float(self.K[1, 2]), 2)],
                k1_k2=[round(float(self.dist[0]), 5), round(float(self.dist[1]), 5)],
                rms_px=finite_or_none(self.rms_px, 3),
                focal_std_pct=finite_or_none(self.focal_std_pct, 3),
                pp_std_px=finite_or_none(self.pp_std_px, 2),
                tilt_spread_deg=finite_or_none(self.tilt_spread_deg, 1),
            )
        return out


def board_views(tracks: Tracks, video: str, board: CharucoBoard) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The frames of `video` that see at least MIN_CORNERS corners not all on one line: board positions (N, 3)
    float32 and pixels (N, 2) float32 per view, in frame order."""
    positions = board_corner_positions(board)
    rows = np.flatnonzero((np.asarray(tracks.video) == video) & np.isin(np.asarray(tracks.point), list(positions)))
    rows = rows[np.argsort(np.asarray(tracks.frame)[rows], kind="stable")]  # by frame, file order within one
    _, starts = np.unique(np.asarray(tracks.frame)[rows], return_index=True)
    objects: list[np.ndarray] = []
    pixels: list[np.ndarray] = []
    for here in np.split(rows, starts[1:]):
        xy = tracks.xy[here]
        finite = np.isfinite(xy).all(axis=1)
        if finite.sum() < MIN_CORNERS:
            continue
        on_board = np.array([positions[str(tracks.point[i])] for i in here[finite]])
        if np.ptp(on_board[:, 2]) > 0:  # both faces of a two-sided board in one frame: not one plane
            continue
        on_board[:, 2] = 0.0  # a back face's plane, moved onto the front's: the intrinsics do not see it
        spread = np.linalg.svd(on_board[:, :2] - on_board[:, :2].mean(axis=0), compute_uv=False)
        if spread[1] < 0.5 * board.square_size:  # one row or column of corners: no homography
            continue
        seen = np.linalg.svd(xy[finite] - xy[finite].mean(axis=0), compute_uv=False)
        if seen[1] < 1.0:  # pixels on one line or one spot (an exporter's 0, 0): no view, and OpenCV would raise
            continue
        objects.append(on_board.astype(np.float32))
        pixels.append(xy[finite].astype(np.float32))
    return objects, pixels


def calibrate_from_board(tracks: Tracks, video: str, size: tuple[int, int], board: CharucoBoard) -> BoardIntrinsics:
    """`video`'s intrinsics (`size` = (width, height) in its pixels) from its views of `board` in `tracks`."""
    objects, pixels = board_views(tracks, video, board)
    if len(objects) < MIN_VIEWS:
        return BoardIntrinsics(
            name=video,
            views=len(objects),
            used=False,
            why=f"{len(objects)} frames see {MIN_CORNERS} or more board corners off one line; {MIN_VIEWS} needed",
        )
    if len(objects) > MAX_VIEWS:
        keep = np.linspace(0, len(objects) - 1, MAX_VIEWS).round().astype(int)
        objects, pixels = [objects[i] for i in keep], [pixels[i] for i in keep]
    try:
        fit = _fit(objects, pixels, size)
        per_view = fit[3]
        outliers = per_view > max(OUTLIER_VIEW * float(np.median(per_view)), MAX_RMS_PX)
        if outliers.any() and (~outliers).sum() >= MIN_VIEWS:
            objects = [o for o, bad in zip(objects, outliers, strict=True) if not bad]
            pixels = [p for p, bad in zip(pixels, outliers, strict=True) if not bad]
            fit = _fit(objects, pixels, size)
    except cv2.error as error:
        why = f"OpenCV's board calibration failed ({str(error).strip().splitlines()[-1]})"
        return BoardIntrinsics(name=video, views=len(objects), used=False, why=why)
    rms, K, dist, _, std, spread = fit
    focal_std = float(max(std[0], std[1])) / float(K[0, 0]) if K[0, 0] > 0 else math.inf
    pp_std = float(max(std[2], std[3]))
    result = BoardIntrinsics(
        name=video,
        views=len(objects),
        used=False,
        K=K,
        dist=np.array([dist[0], dist[1], 0.0, 0.0, 0.0]),
        rms_px=float(rms),
        focal_std_pct=100.0 * focal_std,
        pp_std_px=pp_std,
        tilt_spread_deg=spread,
    )
    long_side = max(size)
    inside = 0 <= K[0, 2] <= size[0] and 0 <= K[1, 2] <= size[1] and 0.1 * long_side < K[0, 0] < 10 * long_side
    if not np.isfinite(rms) or rms > MAX_RMS_PX:
        result.why = f"the board fit's reprojection error is {rms:.2f} px (over {MAX_RMS_PX}): wrong corners or lens"
    elif spread < MIN_TILT_SPREAD_DEG:
        result.why = (
            f"the board is seen at one orientation (its views' normals differ by at most {spread:.0f} deg, "
            f"{MIN_TILT_SPREAD_DEG:.0f} needed): tilt it towards and away from the camera"
        )
    elif not (focal_std <= MAX_FOCAL_STD and pp_std <= MAX_PP_STD * long_side):
        more = "at more angles and distances" if focal_std > MAX_FOCAL_STD else "near every edge of the image too"
        result.why = (
            f"the views do not determine the intrinsics (focal +-{100 * focal_std:.1f} %, principal point "
            f"+-{pp_std:.0f} px, of at most {100 * MAX_FOCAL_STD:g} % and {MAX_PP_STD * long_side:.0f} px): show the "
            f"board {more}"
        )
    elif not inside:
        result.why = f"implausible intrinsics (focal {K[0, 0]:.0f} px, principal point {K[0, 2]:.0f}, {K[1, 2]:.0f})"
    else:
        result.used = True
    return result


def _fit(
    objects: list[np.ndarray], pixels: list[np.ndarray], size: tuple[int, int]
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """(rms, K, dist (k1, k2, ...), per-view rms (N,), std of fx, fy, cx, cy, ..., the largest angle between two
    views' board normals in degrees) of Zhang's fit."""
    width, height = size
    guess = np.array([[max(size), 0.0, (width - 1) / 2], [0.0, max(size), (height - 1) / 2], [0.0, 0.0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    rms, K, dist, rvecs, _, std, _, per_view = cv2.calibrateCameraExtended(
        objects, pixels, (width, height), guess, np.zeros(5), flags=FLAGS, criteria=criteria
    )
    normals = np.array([cv2.Rodrigues(np.asarray(r, float))[0][:, 2] for r in rvecs])
    cosines = np.clip(normals @ normals.T, -1.0, 1.0)
    spread = float(np.degrees(np.arccos(cosines.min())))
    dist = np.asarray(dist, float).ravel()
    return float(rms), np.asarray(K, float), dist, np.ravel(per_view), np.ravel(std), spread


def board_scale(tracks: Tracks, videos: list[str], board: CharucoBoard) -> tuple[str, str, float] | None:
    """(corner A, corner B, metres) for the subject path's scale: of the corner pairs that at least two of
    `videos` see together in SCALE_FRAMES or more frames, the farthest apart on the board; None when no pair
    qualifies."""
    positions = board_corner_positions(board)
    seen: dict[str, dict[str, set[int]]] = {}
    for video, frame, point, xy in zip(tracks.video, tracks.frame, tracks.point, tracks.xy, strict=True):
        if video in videos and point in positions and np.isfinite(xy).all():
            seen.setdefault(str(point), {}).setdefault(str(video), set()).add(int(frame))
    best: tuple[float, str, str] | None = None
    for a, b in itertools.combinations(sorted(seen), 2):
        together = [len(seen[a][v] & seen[b].get(v, set())) for v in seen[a]]
        if sum(n >= SCALE_FRAMES for n in together) < 2:
            continue
        distance = float(np.linalg.norm(positions[a] - positions[b]))
        if best is None or distance > best[0]:
            best = (distance, a, b)
    return None if best is None else (best[1], best[2], best[0])


__all__ = ["BoardIntrinsics", "board_scale", "board_views", "calibrate_from_board"]
