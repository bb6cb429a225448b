"""A known board's views: each camera's intrinsics (Zhang) and the scale, against a projection we control."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from board_video import write_video

from dynrecon.cli import main
from sfm.board import MIN_VIEWS, board_scale, calibrate_from_board
from sfm.frames import Resize
from sfm.options import RegisterOptions, SubjectPath
from sfm.plan import FramePose, VideoPlan
from sfm.register_subject import _with_board, pose_from_subject
from sfm.video import ProbedVideo
from tracking.charuco import CharucoBoard, board_corner_positions
from tracking.tracks import Tracks

BOARD = CharucoBoard(columns=4, rows=5, square_size=0.054, marker_size=0.0405, dictionary="DICT_4X4_1000")
SIZE = (1280, 720)
K_TRUE = np.array([[900.0, 0.0, 655.0], [0.0, 900.0, 350.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.30, 0.10, 0.0, 0.0, 0.0])


def _board_poses(rng: np.random.Generator, count: int, tilt_deg: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """cam_from_board (rvec, tvec) of a board waved 0.6-1.4 m in front of the camera, tilted up to tilt_deg."""
    poses = []
    centre = np.array([0.108, 0.135, 0.0])  # the inner corners' middle
    for _ in range(count):
        angles = np.radians(rng.uniform(-tilt_deg, tilt_deg, 3) * np.array([1, 1, 0.5]))
        R = cv2.Rodrigues(angles)[0]
        depth = rng.uniform(0.6, 1.4)
        t = np.array([rng.uniform(-0.25, 0.25) * depth, rng.uniform(-0.12, 0.12) * depth, depth]) - R @ centre
        poses.append((cv2.Rodrigues(R)[0], t))
    return poses


def _tracks(
    video: str,
    poses: list[tuple[np.ndarray, np.ndarray]],
    noise_px: float,
    seed: int = 0,
    board: CharucoBoard = BOARD,
    back: bool = False,
) -> Tracks:
    """Projected corners; `back`: the back face's (`corner_<id>_back`) of a board with a thickness."""
    rng = np.random.default_rng(seed)
    positions = board_corner_positions(board)
    names = [n for n in positions if n.endswith("_back") == back]
    corners = np.array([positions[n] for n in names])
    rows_video, rows_frame, rows_point, rows_xy = [], [], [], []
    for frame, (rvec, tvec) in enumerate(poses):
        xy = np.asarray(cv2.projectPoints(corners, rvec, tvec, K_TRUE, DIST_TRUE)[0], float).reshape(-1, 2)
        xy += rng.normal(0.0, noise_px, xy.shape)
        seen = (xy[:, 0] >= 0) & (xy[:, 0] < SIZE[0]) & (xy[:, 1] >= 0) & (xy[:, 1] < SIZE[1])
        for i in np.flatnonzero(seen):
            rows_video.append(video)
            rows_frame.append(frame)
            rows_point.append(names[i])
            rows_xy.append(xy[i])
    return Tracks(video=rows_video, frame=np.array(rows_frame), point=rows_point, xy=np.array(rows_xy))


def test_intrinsics_from_the_board_views() -> None:
    tracks = _tracks("cam", _board_poses(np.random.default_rng(1), 40, tilt_deg=35), noise_px=0.3)
    found = calibrate_from_board(tracks, "cam", SIZE, BOARD)
    assert found.used, found.why
    assert found.K is not None and found.dist is not None
    assert abs(found.K[0, 0] / K_TRUE[0, 0] - 1) < 0.01
    np.testing.assert_allclose(found.K[:2, 2], K_TRUE[:2, 2], atol=10.0)
    assert abs(found.dist[0] - DIST_TRUE[0]) < 0.03
    assert found.rms_px is not None and found.rms_px < 0.5
    report = found.to_json()
    assert report["used"] and report["views"] == 40 and 0 < report["focal_std_pct"] < 1


def test_back_face_views_of_a_thick_board() -> None:
    """The back face's corners lie on their own plane (z = +thickness): its views calibrate like the front's."""
    thick = CharucoBoard(**{**vars(BOARD), "thickness": 0.01})
    poses = _board_poses(np.random.default_rng(1), 40, tilt_deg=35)
    front = _tracks("cam", poses[:20], noise_px=0.3, board=thick)
    back = _tracks("cam", poses[20:], noise_px=0.3, board=thick, back=True)
    tracks = Tracks(
        video=[*front.video, *back.video],
        frame=np.r_[front.frame, back.frame + 20],
        point=[*front.point, *back.point],
        xy=np.r_[front.xy, back.xy],
    )
    found = calibrate_from_board(tracks, "cam", SIZE, thick)
    assert found.used and found.views == 40, found.why
    assert found.K is not None and abs(found.K[0, 0] / K_TRUE[0, 0] - 1) < 0.01
    assert found.rms_px is not None and found.rms_px < 0.5


def test_a_misread_view_is_left_out() -> None:
    tracks = _tracks("cam", _board_poses(np.random.default_rng(2), 30, tilt_deg=35), noise_px=0.3)
    swapped = np.flatnonzero(tracks.frame == 3)
    # the corners of one frame read with the wrong ids (a reversed order is the board turned 180 deg: no error)
    tracks.xy[swapped] = tracks.xy[np.random.default_rng(0).permutation(swapped)]
    found = calibrate_from_board(tracks, "cam", SIZE, BOARD)
    # that view pulls the first fit, so a few good views can leave with it
    assert found.used and 25 <= found.views <= 29, found.to_json()
    assert found.K is not None and abs(found.K[0, 0] / K_TRUE[0, 0] - 1) < 0.02
    assert found.rms_px is not None and found.rms_px < 0.5


def test_views_that_do_not_determine_the_focal_are_refused() -> None:
    # The board always square to the camera, at one distance: focal length and distance trade off.
    poses = [
        (np.zeros(3), np.array([x, y, 1.0]) - np.array([0.108, 0.135, 0.0]))
        for x, y in np.random.default_rng(3).uniform(-0.2, 0.2, (30, 2))
    ]
    found = calibrate_from_board(_tracks("cam", poses, noise_px=0.3), "cam", SIZE, BOARD)
    assert not found.used and "one orientation" in (found.why or ""), found.to_json()


def test_views_on_one_side_of_the_image_leave_the_principal_point_undetermined() -> None:
    """Every view in the right third of the image: the focal is determined (under 3 %) but the principal point is
    not, and one further than real principal points lie from the image centre is no better than the centre that the
    subject path holds (caliscope's older office session: +-35 px and 96 px off, its rotations 2.5 x the centre's)."""
    rng = np.random.default_rng(2)
    centre = np.array([0.108, 0.135, 0.0])
    poses = []
    for _ in range(60):
        R = cv2.Rodrigues(np.radians(rng.uniform(-30, 30, 3) * np.array([1, 1, 0.5])))[0]
        depth = rng.uniform(0.9, 1.4)
        t = np.array([rng.uniform(0.28, 0.38) * depth, rng.uniform(-0.1, 0.1) * depth, depth]) - R @ centre
        poses.append((cv2.Rodrigues(R)[0], t))
    found = calibrate_from_board(_tracks("cam", poses, noise_px=0.6, seed=2), "cam", SIZE, BOARD)
    report = found.to_json()
    assert report["focal_std_pct"] < 3.0 and report["pp_std_px"] > 0.015 * max(SIZE), report
    assert not found.used and "principal point" in (found.why or ""), report


def test_too_few_views_say_how_many() -> None:
    tracks = _tracks("cam", _board_poses(np.random.default_rng(4), MIN_VIEWS - 1, tilt_deg=35), noise_px=0.3)
    found = calibrate_from_board(tracks, "cam", SIZE, BOARD)
    assert not found.used and found.why is not None and f"{MIN_VIEWS} needed" in found.why


def test_scale_pair_is_the_farthest_pair_seen_together() -> None:
    poses = _board_poses(np.random.default_rng(5), 30, tilt_deg=20)
    a, b = _tracks("a", poses, 0.3), _tracks("b", poses, 0.3)
    both = Tracks(
        video=a.video + b.video,
        frame=np.concatenate([a.frame, b.frame]),
        point=a.point + b.point,
        xy=np.concatenate([a.xy, b.xy]),
    )
    pair = board_scale(both, ["a", "b"], BOARD)
    assert pair is not None and pair[:2] == ("corner_0", "corner_11")
    assert pair[2] == pytest.approx(0.054 * np.hypot(2, 3))
    assert board_scale(both, ["a"], BOARD) is None  # one video cannot triangulate


def test_a_bad_board_file_is_a_one_line_error_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    board = tmp_path / "charuco.toml"
    board.write_text("columns = 4\n")
    videos = [str(tmp_path / "a.mp4"), str(tmp_path / "b.mp4")]
    assert main(["register", *videos, "--out", str(tmp_path / "ws"), "--board", str(board)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "charuco.toml" in err and "columns, rows" in err
    assert not (tmp_path / "ws").exists()


def test_a_board_found_in_no_video_keeps_the_last_results(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`register --board` without tracks looks for the corners before it clears anything: a board file that does
    not match the videos is a one-line error, and the last run's results stay."""
    board = tmp_path / "charuco.toml"
    board.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n')
    texture = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, (240, 320), dtype=np.uint8), (5, 5), 1.0)
    videos = [
        str(write_video(tmp_path / f"{name}.avi", [np.roll(texture, k, axis=1)] * 3)) for k, name in enumerate("ab")
    ]
    ws = tmp_path / "ws"
    ws.mkdir()
    kept = {name: f"last run's {name}" for name in ("cameras.json", "background.ply", "register_report.json")}
    for name, text in kept.items():
        (ws / name).write_text(text)
    assert main(["register", *videos, "--out", str(ws), "--board", str(board)]) == 2
    # the last line: in this process, off a terminal, a progress bar's first state is a line of its own before it
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("dynrecon register: error: ") and "in no frame of any video" in err
    assert {name: (ws / name).read_text() for name in kept} == kept and not (ws / "tracks.csv").exists()


def _plans(folder: Path, names: list[str]) -> list[VideoPlan]:
    """Static videos of SIZE, 30 frames each, as register's plan has them."""
    return [
        VideoPlan(
            info=ProbedVideo(
                path=folder / f"{name}.mp4",
                name=name,
                width=SIZE[0],
                height=SIZE[1],
                times=np.arange(30) / 30.0,
                nominal_fps=30.0,
            ),
            resize=Resize(scale=1.0, width=SIZE[0], height=SIZE[1]),
            sfm_frames=np.zeros(0, dtype=np.int64),
            wanted=np.arange(30),
            static=True,
        )
        for name in names
    ]


def test_register_says_when_the_board_is_not_used(tmp_path: Path) -> None:
    plans = _plans(tmp_path, ["a", "b"])
    results = {p.info.name: {0: FramePose(pose=None, reason="not posed")} for p in plans}
    tracks = _tracks("a", _board_poses(np.random.default_rng(8), 12, tilt_deg=35), 0.3)
    warnings: list[str] = []
    options = RegisterOptions(board=tmp_path / "charuco.toml", subject=SubjectPath.NEVER)
    assert pose_from_subject(plans, results, tracks, {}, options, warnings) is None
    assert warnings == [f"--board {tmp_path / 'charuco.toml'}: not used: --subject never"]


def test_register_takes_the_board_only_for_videos_without_intrinsics_or_an_anchor(tmp_path: Path) -> None:
    board_file = tmp_path / "charuco.toml"
    board_file.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n')
    poses = _board_poses(np.random.default_rng(6), 30, tilt_deg=35)
    parts = [_tracks(name, poses, 0.3, seed=i) for i, name in enumerate(["given", "anchor", "free"])]
    tracks = Tracks(
        video=[v for t in parts for v in t.video],
        frame=np.concatenate([t.frame for t in parts]),
        point=[p for t in parts for p in t.point],
        xy=np.concatenate([t.xy for t in parts]),
    )
    plans = _plans(tmp_path, ["given", "anchor", "free"])
    given: dict[str, tuple[np.ndarray, np.ndarray | None]] = {"given": (K_TRUE * 1.1, None)}
    warnings: list[str] = []
    options = RegisterOptions(board=board_file)
    merged, scale, section = _with_board(tracks, plans, given, {"anchor"}, options, warnings)
    # --intrinsics wins, an anchor keeps its background model's, the third video gets the board's; all are checked
    cameras = {c["name"]: c for c in section["cameras"]}
    assert [cameras[n]["used"] for n in ("given", "anchor", "free")] == [False, False, True]
    assert all(c["rms_px"] < 0.5 for c in cameras.values())
    assert merged["given"][0][0, 0] == pytest.approx(990.0) and "anchor" not in merged
    assert abs(merged["free"][0][0, 0] / K_TRUE[0, 0] - 1) < 0.02
    # one anchor fixes the frame only: the board sets the scale, as without anchors; two anchors set it themselves
    assert scale is not None and scale[:2] == ("corner_0", "corner_11") and section["scale"][:2] == list(scale[:2])
    merged, scale, section = _with_board(tracks, plans, given, set(), options, warnings)
    assert scale is not None and scale[:2] == ("corner_0", "corner_11")
    merged, scale, section = _with_board(tracks, plans, given, {"anchor", "given"}, options, warnings)
    assert scale is None and section["scale"] is None and "anchors" in section["scale_why"]
    # a board file that is not the filmed board: no intrinsics, no scale, and a warning says why
    board_file.write_text('columns = 6\nrows = 4\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n')
    merged, scale, section = _with_board(tracks, plans, given, set(), options, warnings)
    assert scale is None and "does not fit" in section["scale_why"] and "free" not in merged
    assert "wrong board file" in warnings[-1]
    # without corner tracks: a warning, nothing changed
    other = Tracks(video=["free"], frame=np.array([0]), point=["head"], xy=np.array([[1.0, 2.0]]))
    merged, scale, section = _with_board(other, plans, given, set(), options, warnings)
    assert merged == given and scale is None and not section["used"] and "no board corners" in warnings[-1]


def test_a_view_of_one_spot_is_left_out_not_a_crash() -> None:
    tracks = _tracks("cam", _board_poses(np.random.default_rng(7), 20, tilt_deg=35), noise_px=0.3)
    tracks.xy[tracks.frame == 2] = 0.0  # an exporter's 0, 0 for every corner of one frame
    found = calibrate_from_board(tracks, "cam", SIZE, BOARD)
    assert found.used and found.views == 19, found.to_json()


def test_a_board_folder_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    videos = [str(tmp_path / "a.mp4"), str(tmp_path / "b.mp4")]
    assert main(["register", *videos, "--out", str(tmp_path / "ws"), "--board", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a readable file" in err
