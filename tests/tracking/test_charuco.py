"""ChArUco corners as tracks: a rendered board with known corners; caliscope's real videos against its calibration."""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from board_video import PPM, render_board, write_video

from dynrecon.errors import InputError
from sfm.calibration import read_calibration
from tracking.charuco import CharucoBoard, board_corner_positions, charuco_tracks, read_charuco_board
from tracking.cli import add_commands
from tracking.importing import ImportOptions, run_import
from tracking.tracks import read_tracks

BOARD = CharucoBoard(
    columns=4, rows=5, square_size=0.054, marker_size=0.0405, dictionary="DICT_4X4_1000", inverted=True
)


def test_read_board_and_corner_positions(tmp_path: Path) -> None:
    path = tmp_path / "charuco.toml"
    path.write_text(
        'columns = 4\nrows = 5\nboard_height = 11.0\nboard_width = 8.5\ndictionary = "DICT_4X4_1000"\n'
        'units = "inch"\naruco_scale = 0.75\nsquare_size_override_cm = 5.4\ninverted = true\n'
    )
    board = read_charuco_board(path)
    assert (board.columns, board.rows, board.dictionary, board.inverted) == (4, 5, "DICT_4X4_1000", True)
    assert board.square_size == pytest.approx(0.054) and board.marker_size == pytest.approx(0.0405)
    positions = board_corner_positions(board)
    assert list(positions) == [f"corner_{i}" for i in range(12)]
    np.testing.assert_allclose(positions["corner_0"], [0.054, 0.054, 0])
    np.testing.assert_allclose(positions["corner_11"], [0.162, 0.216, 0])  # 3 corners a row, 4 rows
    # Without the override the square fills the board: min(11 in / 5, 8.5 in / 4) = 2.125 in.
    path.write_text("[charuco]\ncolumns = 4\nrows = 5\nboard_height = 11.0\nboard_width = 8.5\n")
    assert read_charuco_board(path).square_size == pytest.approx(2.125 * 0.0254)
    path.write_text("columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\nthickness_cm = 0.6\n")
    assert read_charuco_board(path).thickness == pytest.approx(0.006)
    path.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\nthickness_cm = "thin"\n')
    with pytest.raises(InputError, match="thickness_cm"):
        read_charuco_board(path)
    path.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_9X9_1"\n')
    with pytest.raises(InputError, match="unknown aruco dictionary"):
        read_charuco_board(path)


def test_anipose_board_files(tmp_path: Path) -> None:
    """sleap-anipose's board.toml (its test session's file) and anipose's config.toml [calibration]: lengths in mm,
    the dictionary from marker bits and size; the board as aniposelib builds it; a checkerboard is refused."""
    sleap = tmp_path / "board.toml"
    sleap.write_text(
        "board_x = 8\nboard_y = 11\nsquare_length = 24.0\nmarker_length = 18.75\nmarker_bits = 4\ndict_size = 1000"
    )
    board = read_charuco_board(sleap)
    assert (board.columns, board.rows, board.dictionary) == (8, 11, "DICT_4X4_1000")
    assert board.square_size == pytest.approx(0.024) and board.marker_size == pytest.approx(0.01875)
    assert len(board_corner_positions(board)) == 7 * 10
    anipose = tmp_path / "config.toml"
    anipose.write_text(
        'project = "x"\n[calibration]\nboard_type = "charuco"\nboard_size = [10, 7]\nboard_marker_bits = 5\n'
        "board_marker_dict_number = 100\nboard_marker_length = 18.75\nboard_square_side_length = 25\n"
    )
    board = read_charuco_board(anipose)
    assert (board.columns, board.rows, board.dictionary) == (10, 7, "DICT_5X5_100")
    assert board.square_size == pytest.approx(0.025) and board.marker_size == pytest.approx(0.01875)
    anipose.write_text('[calibration]\nboard_type = "checkerboard"\nboard_size = [9, 6]\n')
    with pytest.raises(InputError, match="board_type = 'checkerboard'"):
        read_charuco_board(anipose)
    sleap.write_text("board_x = 8\nboard_y = 11\nsquare_length = 24.0\nmarker_length = 18.75\nmarker_bits = 3\n")
    with pytest.raises(InputError, match="no such aruco dictionary"):
        read_charuco_board(sleap)
    sleap.write_text("board_x = 8\nboard_y = 11\nsquare_length = 24.0\nmarker_length = 30\n")
    with pytest.raises(InputError, match="aruco_scale"):
        read_charuco_board(sleap)  # a marker larger than its square
    anipose.write_text("[calibration]\nboard_size = [10, 7]\nboard_marker_length = 18.75\n")
    with pytest.raises(InputError, match="board_square_side_length = None must be a positive number"):
        read_charuco_board(anipose)


def test_rendered_board(tmp_path: Path) -> None:
    """Corners found where the homography puts them (the image from generateImage has pixel centres at
    (i + 0.5) / ppm metres), in OpenCV's pixel convention: no bias (the other convention is off by ~0.3 px on
    both axes); an empty frame gives no rows."""
    ppm, size = PPM, (640, 480)  # the rendering's print scale
    homographies = []
    for angle, shift in ((0.0, (150, 40)), (0.2, (200, 60)), (-0.3, (120, 90))):
        c, s = np.cos(angle), np.sin(angle)
        homographies.append(np.array([[1.2 * c, -1.2 * s, shift[0]], [1.2 * s, 1.2 * c, shift[1]], [2e-5, 1e-5, 1.0]]))
    frames = render_board(BOARD, homographies, size)
    frames.insert(1, np.full_like(frames[0], 160))
    homographies.insert(1, np.eye(3))
    path = write_video(tmp_path / "cam_a.avi", frames)
    tracks = charuco_tracks([path], BOARD)
    assert set(tracks.video) == {"cam_a"} and set(tracks.extra["source"]) == {"charuco"}
    assert sorted(set(tracks.frame.tolist())) == [0, 2, 3]
    positions = board_corner_positions(BOARD)
    for frame, H in enumerate(homographies):
        rows = np.flatnonzero(tracks.frame == frame)
        if frame == 1:
            continue
        assert len(rows) == 12
        board_px = np.array([positions[tracks.point[r]][:2] * ppm - 0.5 for r in rows])
        expected = cv2.perspectiveTransform(board_px[:, None], H).reshape(-1, 2)
        error = tracks.xy[rows] - expected
        assert np.abs(error.mean(axis=0)).max() < 0.1 and np.abs(error).max() < 0.5, error
    with pytest.raises(InputError, match="found with 13 or more corners in no frame"):
        charuco_tracks([path], BOARD, min_corners=13)  # every frame shows 12
    with pytest.raises(InputError, match="video file not found"):
        charuco_tracks([tmp_path / "missing.mp4"], BOARD)


def test_back_face_of_a_two_sided_board(tmp_path: Path) -> None:
    """A camera behind a two-sided board sees the mirror print: found by the flipped search, each corner where the
    front corner of its id lies (the board seen through a reflecting homography); `corner_<id>_back` with a
    thickness. A front view in the same video is still found unflipped."""
    ppm, size = PPM, (640, 480)  # the rendering's print scale
    width_px = round(BOARD.columns * BOARD.square_size * ppm)
    behind = np.array([[1.1, 0.1, 180], [-0.05, 1.1, 70], [1e-5, 2e-5, 1.0]]) @ np.array(
        [[-1.0, 0, width_px - 1], [0, 1.0, 0], [0, 0, 1.0]]
    )  # board pixel -> image, orientation-reversing
    front = np.array([[1.2, 0, 150], [0, 1.2, 40], [0, 0, 1.0]])
    path = write_video(tmp_path / "cam_c.avi", render_board(BOARD, [behind, front, behind], size))
    tracks = charuco_tracks([path], BOARD)
    positions = board_corner_positions(BOARD)
    assert sorted(set(tracks.frame.tolist())) == [0, 1, 2] and set(tracks.point) == set(positions)
    for frame, H in enumerate((behind, front, behind)):
        rows = np.flatnonzero(tracks.frame == frame)
        assert len(rows) == 12
        board_px = np.array([positions[tracks.point[r]][:2] * ppm - 0.5 for r in rows])
        expected = cv2.perspectiveTransform(board_px[:, None], H).reshape(-1, 2)
        assert np.abs(tracks.xy[rows] - expected).max() < 0.5, tracks.xy[rows] - expected

    thick = CharucoBoard(**{**vars(BOARD), "thickness": 0.005})
    named = charuco_tracks([path], thick)
    back = {str(p) for p, f in zip(named.point, named.frame, strict=True) if f != 1}
    assert back == {f"corner_{i}_back" for i in range(12)}
    assert {str(p) for p, f in zip(named.point, named.frame, strict=True) if f == 1} == set(positions)
    thick_positions = board_corner_positions(thick)
    np.testing.assert_allclose(thick_positions["corner_4_back"], positions["corner_4"] + [0, 0, 0.005])


def test_import_tracks_charuco(tmp_path: Path) -> None:
    path = write_video(
        tmp_path / "cam_b.avi", render_board(BOARD, [np.array([[1.0, 0, 100], [0, 1.0, 20], [0, 0, 1]])], (640, 480))
    )
    board = tmp_path / "charuco.toml"
    board.write_text(
        'columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n'
        "aruco_scale = 0.75\ninverted = true\n"
    )
    out = tmp_path / "tracks.csv"
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())  # this stage's commands only: `dynrecon` loads every stage
    args = parser.parse_args(["import-tracks", str(path), "--board", str(board), "--out", str(out)])
    assert args.func(args) == 0
    tracks = read_tracks(out)
    assert len(tracks) == 12 and set(tracks.extra["source"]) == {"charuco"}
    assert set(tracks.point) == set(board_corner_positions(board))
    args = parser.parse_args(["import-tracks", str(path), "--format", "charuco", "--out", str(out)])
    with pytest.raises(InputError, match="ChArUco corners need the board"):
        args.func(args)


def _triangulate(normalized: np.ndarray, seen: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """DLT for G points at once: normalized (G, C, 2) image points, seen (G, C), poses (C, 3, 4) -> (G, 3)."""
    rows = normalized[..., :, None] * poses[None, :, 2:3, :] - poses[None, :, :2, :]  # (G, C, 2, 4)
    rows = rows * seen[..., None, None]
    _, _, vt = np.linalg.svd(rows.reshape(len(rows), -1, 4))
    X = vt[:, -1]
    return X[:, :3] / X[:, 3:]


@pytest.mark.shared
def test_caliscope_corners_reproject(shared_dir: Path) -> None:
    """Corners triangulated with caliscope's own calibration, per sync step of timestamps.csv, reproject within a
    few pixels in every camera; and the board's corner spacing comes out at its 5.4 cm squares."""
    office = shared_dir / "data" / "videos" / "caliscope_office"
    cameras = read_calibration(office / "camera_array.toml")
    videos = [office / "calibration" / "extrinsic" / f"{c.name}.mp4" for c in cameras]
    start = time.perf_counter()
    tracks = charuco_tracks(videos, office / "charuco.toml")
    elapsed = time.perf_counter() - start
    names = [c.name for c in cameras]
    cam = np.array([names.index(v) for v in tracks.video])
    corner = np.array([int(p.removeprefix("corner_")) for p in tracks.point])

    good = {}
    for c, name in enumerate(names):
        _, counts = np.unique(tracks.frame[cam == c], return_counts=True)
        good[name] = int((counts >= 6).sum())
    print(f"charuco: {elapsed:.1f} s for 4 videos; frames with >= 6 corners: {good}")
    assert all(n >= 20 for n in good.values()), good

    # Sync steps: the videos hold exactly the frames listed (frame_index ascending), one row per camera and step.
    with open(office / "calibration" / "extrinsic" / "timestamps.csv", newline="") as handle:
        rows = [(int(r["sync_index"]), int(r["cam_id"]), int(r["frame_index"])) for r in csv.DictReader(handle)]
    sync_of = np.full((len(names), 1 + max(r[2] for r in rows)), -1)
    for c in range(len(names)):
        listed = sorted((f, s) for s, cid, f in rows if cid == c)
        for decoded, (_, sync) in enumerate(listed):
            sync_of[c, decoded] = sync
    sync = sync_of[cam, tracks.frame]
    assert np.all(sync >= 0)

    normalized = np.zeros((len(tracks), 2))
    for c, camera in enumerate(cameras):
        mask = cam == c
        normalized[mask] = cv2.undistortPoints(tracks.xy[mask][:, None], camera.K, camera.dist).reshape(-1, 2)
    keys, group = np.unique(np.c_[sync, corner], axis=0, return_inverse=True)
    group = group.ravel()
    obs = np.zeros((len(keys), len(names), 2))
    seen = np.zeros((len(keys), len(names)))
    obs[group, cam] = normalized
    seen[group, cam] = 1
    multi = seen.sum(1) >= 2
    poses = np.array([np.c_[c.R, c.t] for c in cameras])
    X = np.full((len(keys), 3), np.nan)
    X[multi] = _triangulate(obs[multi], seen[multi], poses)

    use = multi[group]
    errors = np.zeros(len(tracks))
    for c, camera in enumerate(cameras):
        mask = use & (cam == c)
        projected, _ = cv2.projectPoints(X[group[mask]], cv2.Rodrigues(camera.R)[0], camera.t, camera.K, camera.dist)
        errors[mask] = np.linalg.norm(projected.reshape(-1, 2) - tracks.xy[mask], axis=1)
    median = float(np.median(errors[use]))
    per_camera = {names[c]: round(float(np.median(errors[use & (cam == c)])), 2) for c in range(len(names))}
    print(f"charuco: {int(multi.sum())} corners in >= 2 views; reprojection median {median:.2f} px {per_camera}")
    assert median < 2.0, per_camera

    # Neighbouring corners on one row are one square apart (5.4 cm) in the triangulated 3D points.
    by_key = {(int(s), int(k)): X[i] for i, (s, k) in enumerate(keys) if multi[i]}
    spacing = [
        np.linalg.norm(by_key[(s, k + 1)] - x) for (s, k), x in by_key.items() if k % 3 != 2 and (s, k + 1) in by_key
    ]
    print(f"charuco: neighbouring corners {np.median(spacing) * 100:.2f} cm apart (median of {len(spacing)})")
    assert len(spacing) > 50 and abs(np.median(spacing) - 0.054) < 0.003, np.median(spacing)


def test_import_goes_on_when_one_video_never_shows_the_board(tmp_path: Path) -> None:
    """A camera that never saw the board adds no rows (a warning); only a board found in no video is an error."""
    size = (640, 480)
    shown = render_board(BOARD, [np.array([[1.2, 0.0, 150.0], [0.0, 1.2, 40.0], [2e-5, 1e-5, 1.0]])], size)
    paths = {"cam_a": shown * 3, "cam_b": [np.full_like(shown[0], 160)] * 3}
    for name, frames in paths.items():
        write_video(tmp_path / f"{name}.avi", frames)
    board = tmp_path / "charuco.toml"
    board.write_text(
        f"columns = {BOARD.columns}\nrows = {BOARD.rows}\nsquare_size_override_cm = {BOARD.square_size * 100}\n"
        f'aruco_scale = {BOARD.marker_size / BOARD.square_size}\ndictionary = "{BOARD.dictionary}"\n'
        "inverted = true\n"
    )
    out = run_import([tmp_path / "cam_a.avi", tmp_path / "cam_b.avi"], tmp_path / "t.csv", ImportOptions(board=board))
    assert set(read_tracks(out).video) == {"cam_a"}
    with pytest.raises(InputError, match="found in no frame of any video"):
        run_import([tmp_path / "cam_b.avi"], tmp_path / "u.csv", ImportOptions(board=board))
    # two phones' IMG_0001: refused before any decoding, naming the name (not two detections of one corner)
    for phone in ("phone_a", "phone_b"):
        (tmp_path / phone).mkdir()
        (tmp_path / phone / "IMG_0001.avi").write_bytes((tmp_path / "cam_a.avi").read_bytes())
    twice = [tmp_path / "phone_a" / "IMG_0001.avi", tmp_path / "phone_b" / "IMG_0001.avi"]
    with pytest.raises(InputError, match="video name 'IMG_0001' is used twice"):
        run_import(twice, tmp_path / "v.csv", ImportOptions(board=board))
