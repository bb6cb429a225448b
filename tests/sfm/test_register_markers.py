"""Tracks register finds itself: the corners of markers in view, against rendered videos we control."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from board_video import render_board, write_video

from dynrecon.cli import main
from sfm.frames import Resize
from sfm.plan import VideoPlan
from sfm.register_markers import MARKER_TRACKS, markers_in_samples, smallest_dictionary, tracks_from_markers
from sfm.video import ProbedVideo
from tracking.charuco import CharucoBoard
from tracking.tracks import read_tracks

BOARD = CharucoBoard(columns=4, rows=5, square_size=0.054, marker_size=0.040, dictionary="DICT_4X4_1000", inverted=True)
SIZE = (640, 480)
FRAMES = 6


def _plan(path: Path) -> VideoPlan:
    return VideoPlan(
        info=ProbedVideo(
            path=path,
            name=path.stem,
            width=SIZE[0],
            height=SIZE[1],
            times=np.arange(FRAMES) / 10.0,
            nominal_fps=10.0,
        ),
        resize=Resize(scale=1.0, width=SIZE[0], height=SIZE[1]),
        sfm_frames=np.zeros(0, dtype=np.int64),
        wanted=np.arange(FRAMES),
        static=True,
    )


def _board_video(path: Path, scale: float) -> Path:
    moves = [np.array([[scale, 0, 100 + 12 * i], [0, scale, 40 + 5 * i], [0, 0, 1]]) for i in range(FRAMES)]
    return write_video(path, render_board(BOARD, moves, SIZE))


def test_markers_two_videos_share_are_the_tracks(tmp_path: Path) -> None:
    """Two videos show the board, a third a lone marker only it sees, a fourth none: the tracks are the board's
    10 markers x 4 corners in the two videos, every frame, written to marker_tracks.csv and read back."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    lone = np.full((SIZE[1], SIZE[0]), 255, dtype=np.uint8)
    for k, marker_id in enumerate((500, 501, 502)):  # three markers: the dictionary is in view in cam_c too
        lone[100:180, 60 + 150 * k : 140 + 150 * k] = cv2.aruco.generateImageMarker(dictionary, marker_id, 80)
    texture = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, (SIZE[1], SIZE[0]), dtype=np.uint8), (5, 5), 1)
    paths = [
        _board_video(tmp_path / "cam_a.avi", 1.3),
        _board_video(tmp_path / "cam_b.avi", 1.1),
        write_video(tmp_path / "cam_c.avi", [lone] * FRAMES),
        write_video(tmp_path / "cam_d.avi", [texture] * FRAMES),
    ]
    tracks, note = tracks_from_markers([_plan(p) for p in paths], tmp_path)
    assert tracks is not None and note is not None
    # searched with the smallest dictionary of the family that holds the board's ids 0-9 (the same markers)
    assert note["dictionary"] == "DICT_4X4_50" and note["frames"] == {"cam_a": FRAMES, "cam_b": FRAMES}
    assert note["points"] == 40 and note["file"] == str(tmp_path / MARKER_TRACKS)
    assert sorted(set(tracks.point)) == sorted(f"marker_{i}_{k}" for i in range(10) for k in range(4))
    assert len(tracks) == 2 * FRAMES * 40
    again = read_tracks(tmp_path / MARKER_TRACKS).canonical()
    np.testing.assert_array_equal(again.xy, tracks.xy)  # this run uses what a later run reads


def test_markers_in_one_video_are_no_tracks(tmp_path: Path) -> None:
    paths = [_board_video(tmp_path / "cam_a.avi", 1.3), tmp_path / "missing.avi"]
    assert tracks_from_markers([_plan(p) for p in paths], tmp_path) == (None, None)
    assert not (tmp_path / MARKER_TRACKS).exists()


def test_a_failure_on_markers_says_the_tracks_were_the_markers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A board that stands still in two views with no textured background: no background model, and the subject
    path refuses two self-calibrated cameras; the one-line error says the tracks were the markers register found."""
    views = (
        np.array([[1.2, 0.1, 150], [0.05, 1.1, 40], [1e-4, 0, 1]]),
        np.array([[1.0, -0.2, 200], [0.1, 1.2, 60], [-1e-4, 1e-4, 1]]),
    )
    videos = [
        str(write_video(tmp_path / f"{name}.avi", render_board(BOARD, [H] * 20, SIZE)))
        for name, H in zip("ab", views, strict=True)
    ]
    assert main(["register", *videos, "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "two cameras with self-calibrated focal lengths" in err
    assert f"DICT_4X4_50 markers in view, {tmp_path / 'ws' / MARKER_TRACKS}" in err
    report = json.loads((tmp_path / "ws" / "register_report.json").read_text())
    assert report["subject"]["markers"]["frames"] == {"a": 20, "b": 20}
    # the markers stand still: the motion test keeps them as background (static), instead of masking all it sees
    assert [v["camera"] for v in report["videos"]] == ["static", "static"]
    # given back as the tracks (what `run` advises), the file is read, and never removed as an earlier run's
    markers = tmp_path / "ws" / MARKER_TRACKS
    before = markers.read_bytes()
    assert main(["register", *videos, "--out", str(tmp_path / "ws"), "--tracks", str(markers)]) == 2
    assert markers.read_bytes() == before


def test_the_smallest_dictionary_that_holds_the_ids_is_searched() -> None:
    assert smallest_dictionary("DICT_4X4_1000", 9) == "DICT_4X4_50"
    assert smallest_dictionary("DICT_5X5_1000", 45) == "DICT_5X5_100"  # ids past the largest seen: 1.5x margin
    assert smallest_dictionary("DICT_6X6_1000", 900) == "DICT_6X6_1000"
    assert smallest_dictionary("DICT_APRILTAG_36h11", 3) == "DICT_APRILTAG_36h11"  # no smaller one of its family


def test_the_motion_test_masks_markers_that_move_and_keeps_those_that_stand_still() -> None:
    """A board waved in front of a tripod is a subject for the motion test to mask (its corners per sampled frame,
    in original pixels at half the work scale); the same board standing still is background (None)."""
    moving = [np.array([[1.3, 0, 100 + 20 * i], [0, 1.3, 40 + 8 * i], [0, 0, 1]]) for i in range(FRAMES)]
    grays = np.stack([cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in render_board(BOARD, moving, SIZE)])
    frames = np.arange(FRAMES) * 10
    found = markers_in_samples(frames, grays, 0.5)
    assert found is not None and sorted(found) == frames.tolist()
    assert all(len(points) == 40 for points in found.values())
    # frame 0's board spans x 100-380 at the work size: 200-760 px in the original
    assert found[0][:, 0].min() > 190 and found[0][:, 0].max() < 770
    still = np.stack([grays[0]] * FRAMES)
    assert markers_in_samples(frames, still, 0.5) is None
