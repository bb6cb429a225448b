"""Video names in tracks.csv spelled differently from the videos' (`--video back.mp4`, `Cam01` for `cam_1`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import pytest

from dynrecon.names import name_key
from tracking.cli import _video_name, add_commands
from tracking.tracks import Tracks, matched_to_videos, read_tracks


def _tracks(*videos: str) -> Tracks:
    return Tracks.from_rows([(video, 0, "nose", 1.0, 2.0) for video in videos])


def test_name_key_ignores_case_separators_zeros_and_suffix() -> None:
    assert {name_key(n) for n in ("back.mp4", "Back", "BACK.MOV", "back")} == {"back"}
    assert {name_key(n) for n in ("cam_01", "Cam1", "cam-1.avi", "CAM001")} == {"cam-1"}
    assert name_key("cam10") != name_key("cam1") and name_key("back.txt") != name_key("back")
    assert name_key("cam1_2") != name_key("cam12") and name_key("cam_0_1") != name_key("cam1")
    assert name_key("Kamera_ä") != name_key("Kamera_ö")


def test_unknown_video_names_are_matched_when_unambiguous(caplog: pytest.LogCaptureFixture) -> None:
    tracks = _tracks("back.mp4", "Cam01", "side", "elsewhere")
    with caplog.at_level(logging.WARNING, logger="tracking.tracks"):
        matched = matched_to_videos(tracks, ["back", "cam_1", "side", "top"])
    assert matched.video == ["back", "cam_1", "side", "elsewhere"]  # no video matches "elsewhere": kept
    assert "'back.mp4' taken as the video 'back'" in caplog.text and "elsewhere" not in caplog.text
    same = _tracks("back", "side")
    assert matched_to_videos(same, ["back", "side"]) is same
    # names that would join another video's rows, or match two videos, stay as they are
    assert matched_to_videos(_tracks("back.mp4", "back"), ["back"]).video == ["back.mp4", "back"]
    assert matched_to_videos(_tracks("cam1"), ["cam01", "cam_1"]).video == ["cam1"]
    assert matched_to_videos(_tracks("cam1.mp4", "cam_1"), ["cam01"]).video == ["cam1.mp4", "cam_1"]


def test_import_video_option_takes_a_file_or_a_name(tmp_path: Path) -> None:
    assert _video_name("videos/back.mp4") == "back" and _video_name("back.MOV") == "back"
    assert _video_name("back") == "back" and _video_name("take.2") == "take.2" and _video_name(None) is None
    assert _video_name("videos/session.01") == "session.01"
    plain = tmp_path / "detections.csv"
    plain.write_text("video,frame,point,x,y\nrecorded,0,nose,1,2\n")
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(dest="command"))
    out = tmp_path / "tracks.csv"
    args = parser.parse_args(["import-tracks", str(plain), "--video", str(tmp_path / "back.mp4"), "--out", str(out)])
    assert args.func(args) == 0
    assert read_tracks(out).video == ["back"]
