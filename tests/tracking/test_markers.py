"""Fiducial markers' corners as tracks, without a board file: a rendered ChArUco board with known marker corners."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from board_video import PPM, render_board, write_video

from dynrecon.errors import InputError
from tracking.charuco import CharucoBoard
from tracking.markers import find_markers, marker_detector, marker_point, marker_tracks

# markers of a whole number of printed pixels (PPM): a marker of 40.5 px is drawn 40 or 41 px wide
BOARD = CharucoBoard(columns=4, rows=5, square_size=0.054, marker_size=0.040, dictionary="DICT_4X4_1000", inverted=True)
SIZE = (640, 480)


def _expected(H: np.ndarray) -> dict[str, np.ndarray]:
    """marker_<id>_<k> -> where the homography puts that corner (OpenCV's pixel convention)."""
    board = BOARD.opencv()
    expected = {}
    for marker_id, corners in zip(np.ravel(board.getIds()), board.getObjPoints(), strict=True):
        board_px = np.asarray(corners, dtype=float).reshape(4, 3)[:, :2] * PPM - 0.5
        image = cv2.perspectiveTransform(board_px[:, None], H).reshape(4, 2)
        expected |= {marker_point(int(marker_id), k): image[k] for k in range(4)}
    return expected


def _homography(angle: float, shift: tuple[float, float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.2 * c, -1.2 * s, shift[0]], [1.2 * s, 1.2 * c, shift[1]], [2e-5, 1e-5, 1.0]])


def test_rendered_markers_are_named_by_id_where_the_homography_puts_them(tmp_path: Path) -> None:
    """Every corner of the board's 10 markers, named by marker id and corner, within half a pixel of the truth;
    an empty frame gives no rows; a missing video and an unknown dictionary are one-line errors."""
    homographies = [_homography(0.0, (150, 40)), np.eye(3), _homography(0.25, (220, 60)), _homography(-0.3, (120, 90))]
    frames = render_board(BOARD, [h for i, h in enumerate(homographies) if i != 1], SIZE)
    frames.insert(1, np.full_like(frames[0], 160))
    tracks = marker_tracks([write_video(tmp_path / "cam_a.avi", frames)], "DICT_4X4_1000")
    assert set(tracks.video) == {"cam_a"} and set(tracks.extra["source"]) == {"marker"}
    assert sorted(set(tracks.frame.tolist())) == [0, 2, 3]
    for frame, H in enumerate(homographies):
        if frame == 1:
            continue
        rows = np.flatnonzero(tracks.frame == frame)
        expected = _expected(H)
        assert {tracks.point[r] for r in rows} == set(expected)  # 10 markers x 4 corners
        error = tracks.xy[rows] - np.array([expected[tracks.point[r]] for r in rows])
        assert np.abs(error).max() < 0.5, error
    with pytest.raises(InputError, match="video file not found"):
        marker_tracks([tmp_path / "missing.mp4"], "DICT_4X4_1000")
    with pytest.raises(InputError, match="unknown marker dictionary 'DICT_9X9_1'"):
        marker_tracks([tmp_path / "cam_a.avi"], "DICT_9X9_1")


def test_the_mirror_print_of_a_two_sided_board_is_read_flipped(tmp_path: Path) -> None:
    """A camera behind a two-sided board sees the mirror print: each marker corner is named as the front's that
    lies in front of it, where the reflecting homography puts that front corner."""
    width_px = round(BOARD.columns * BOARD.square_size * PPM)
    behind = _homography(0.1, (180, 70)) @ np.array([[-1.0, 0, width_px - 1], [0, 1.0, 0], [0, 0, 1.0]])
    tracks = marker_tracks([write_video(tmp_path / "cam_b.avi", render_board(BOARD, [behind], SIZE))], "DICT_4X4_1000")
    expected = _expected(behind)
    assert set(tracks.point) == set(expected)
    error = tracks.xy - np.array([expected[p] for p in tracks.point])
    assert np.abs(error).max() < 0.5, error


def test_a_marker_printed_twice_is_left_out_everywhere(tmp_path: Path) -> None:
    """Two copies of marker 7 cannot be told apart: in a frame that shows both neither is kept, marker 8 beside
    them is; a video that shows the copies one at a time in other frames loses marker 7 there too (its name would
    join two points), with a warning."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)

    def frame(markers: tuple[tuple[int, int], ...]) -> np.ndarray:
        image = np.full((240, 480), 255, dtype=np.uint8)
        for marker_id, x in markers:
            image[70:170, x : x + 100] = cv2.aruco.generateImageMarker(dictionary, marker_id, 100)
        return image

    found = find_markers(frame(((7, 40), (7, 190), (8, 340))), marker_detector("DICT_4X4_1000"), False)
    assert found is not None
    ids, corners, doubled = found
    assert ids.tolist() == [8] and doubled == {7}
    np.testing.assert_allclose(corners[0, 0], [339.5, 69.5], atol=0.3)  # its top-left corner, refined
    frames = [frame(((7, 40), (7, 190), (8, 340))), frame(((7, 40), (9, 190), (8, 340)))]
    other = [frame(((7, 190), (9, 40), (8, 340)))] * 2
    tracks = marker_tracks(
        [write_video(tmp_path / "cam_a.avi", frames), write_video(tmp_path / "cam_b.avi", other)], "DICT_4X4_1000"
    )
    assert {p.rsplit("_", 1)[0] for p in tracks.point} == {"marker_8", "marker_9"}


def test_large_frames_are_searched_small_and_refined_full_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A 2560 x 1440 frame is searched at 1280 x 720 and its corners refined in the full frame: within half a pixel
    of the truth. A video longer than MAX_SEARCHED frames is searched on evenly spaced frames."""
    H = _homography(0.2, (600, 200)) @ np.diag([2.5, 2.5, 1.0])
    path = write_video(tmp_path / "cam_4k.avi", render_board(BOARD, [H] * 5, (2560, 1440)))
    monkeypatch.setattr("tracking.markers.MAX_SEARCHED", 2)  # 5 frames: every 3rd
    tracks = marker_tracks([path], "DICT_4X4_1000")
    assert sorted(set(tracks.frame.tolist())) == [0, 3]
    expected = _expected(H)
    error = tracks.xy - np.array([expected[p] for p in tracks.point])
    assert len(set(tracks.point)) == 40 and np.abs(error).max() < 0.5, error
