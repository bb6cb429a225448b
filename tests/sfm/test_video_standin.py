"""import-calibration without the videos (a lab's calibration and 2D tracks shared without them): VIDEO names,
--fps, frames from the tracks, sizes from the calibration or --size; the same cameras.json as with the videos."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from sfm.calibration import write_toml
from sfm.cameras import read_cameras
from tracking.tracks import Tracks, write_tracks

from .test_calibration_dlt import _rig
from .test_import_calibration import _random_cameras, _write_video


def _tracks(path: Path, last: dict[str, int]) -> Path:
    """A point seen on every 3rd frame of each video up to its `last` frame."""
    rows = [
        (name, frame, "p", 10.0 + frame, 20.0) for name, final in last.items() for frame in [*range(0, final, 3), final]
    ]
    return write_tracks(path, Tracks.from_rows(rows))


def test_videos_named_take_their_frames_from_the_tracks(tmp_path: Path) -> None:
    """Named videos get the frames 0 to their last tracked frame, the rate --fps gives and the calibrated size; a video
    that is here is probed as usual, and its cameras.json entry is the one without stand-ins."""
    cameras = _random_cameras(["cam_0", "cam_1", "cam_2"])
    toml = write_toml(tmp_path / "calibration.toml", cameras)
    _write_video(tmp_path / "cam2.mp4", 7, (64, 48), fps=25.0)
    tracks = _tracks(tmp_path / "tracks.csv", {"cam0": 11, "cam1": 9, "cam2": 5})
    ws = tmp_path / "ws"
    args = ["import-calibration", str(toml), "cam0", "cam1", str(tmp_path / "cam2.mp4"), "--out", str(ws)]
    assert main([*args, "--fps", "25", "--tracks", str(tracks)]) == 0
    videos = read_cameras(ws / "cameras.json").videos
    assert [(v.name, v.width, v.height, v.fps, len(v.frames)) for v in videos] == [
        ("cam0", 64, 48, 25.0, 12),
        ("cam1", 64, 48, 25.0, 10),
        ("cam2", 64, 48, 25.0, 7),  # the file's own frames, not the tracks'
    ]
    # --fps's rate, not measured times: cameras.json gives the rate and the solve fits each name's true one
    assert [{f.time is None for f in v.frames} for v in videos] == [{True}, {True}, {False}]
    for video, camera in zip(videos, cameras, strict=True):
        np.testing.assert_allclose(video.frames[0].K, camera.K)
        np.testing.assert_allclose(video.frames[-1].R, camera.R, atol=1e-9)
    # with every video here, the same cameras for the same frames
    for name, frames in (("cam0", 12), ("cam1", 10)):
        _write_video(tmp_path / f"{name}.mp4", frames, (64, 48), fps=25.0)
    files = [str(tmp_path / f"cam{i}.mp4") for i in range(3)]
    assert main(["import-calibration", str(toml), *files, "--out", str(tmp_path / "ws2")]) == 0
    probed = read_cameras(tmp_path / "ws2" / "cameras.json").videos
    for stood, real in zip(videos, probed, strict=True):
        assert [f.frame for f in stood.frames] == [f.frame for f in real.frames]
        np.testing.assert_allclose(stood.frames[3].K, real.frames[3].K)


def test_the_workspace_tracks_and_a_size_for_a_file_without_one(tmp_path: Path) -> None:
    """DLT coefficients give no image size: --size does; the tracks default to WS/tracks.csv."""
    from tests.dlt_files import coefficients, write_dlt_columns
    from tracking.pixels import DltPixels

    Ks, Rs, ts = _rig()
    table = np.stack([coefficients(K, R, t, DltPixels.OPENCV, 48) for K, R, t in zip(Ks, Rs, ts, strict=True)])
    dlt = write_dlt_columns(tmp_path / "rig_dltCoefs.csv", table)
    ws = tmp_path / "ws"
    ws.mkdir()
    _tracks(ws / "tracks.csv", {"cam1": 4, "cam2": 4, "cam3": 6})
    args = ["import-calibration", str(dlt), "cam1", "cam2", "cam3", "--pixels", "opencv", "--fps", "50"]
    assert main([*args, "--out", str(ws), "--size", "64x48"]) == 0
    videos = read_cameras(ws / "cameras.json").videos
    assert [(v.width, v.height, len(v.frames)) for v in videos] == [(64, 48, 5), (64, 48, 5), (64, 48, 7)]
    np.testing.assert_allclose(videos[0].frames[0].K / videos[0].frames[0].K[2, 2], Ks[0] / Ks[0][2, 2], atol=1e-6)


@pytest.mark.parametrize(
    ("extra", "what"),
    [
        ([], "cam0: no such video (give the video file; where the videos are not here, give --fps"),
        (["--fps", "30"], "no such video, and its frames cannot come from the tracks ("),
        (["--fps", "30", "--tracks", "TRACKS"], "has no tracks of a video 'cam5' (name the videos as the tracks do"),
    ],
)
def test_what_is_missing_is_said_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], what: str
) -> None:
    toml = write_toml(tmp_path / "calibration.toml", _random_cameras(["cam_0", "cam_5"]))
    tracks = _tracks(tmp_path / "tracks.csv", {"cam0": 4})
    extra = [str(tracks) if e == "TRACKS" else e for e in extra]
    args = ["import-calibration", str(toml), "cam0", "cam5", "--out", str(tmp_path / "ws"), *extra]
    assert main(args) == 2
    error = capsys.readouterr().err
    assert what in error and error.count("\n") == 1, error
    assert not (tmp_path / "ws" / "cameras.json").exists()


def test_a_size_that_is_not_one_is_refused_by_the_parser(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as raised:
        main(["import-calibration", "c.toml", "cam0", "--out", str(tmp_path), "--fps", "30", "--size", "64by48"])
    assert raised.value.code == 2
    assert "'64by48' is not WIDTHxHEIGHT" in capsys.readouterr().err


def test_a_size_other_than_the_calibrated_one_scales_k(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """--size 128x96 for cameras calibrated at 64x48: the videos are the calibrated images at twice the size, and K
    is scaled like a probed video's; --tracks without --fps serves nothing and says so."""
    cameras = _random_cameras(["cam_0", "cam_1"])
    toml = write_toml(tmp_path / "calibration.toml", cameras)
    tracks = _tracks(tmp_path / "tracks.csv", {"cam0": 4, "cam1": 4})
    args = ["import-calibration", str(toml), "cam0", "cam1", "--fps", "25", "--tracks", str(tracks)]
    assert main([*args, "--size", "128x96", "--out", str(tmp_path / "ws")]) == 0
    K = read_cameras(tmp_path / "ws" / "cameras.json").videos[0].frames[0].K
    expected = cameras[0].K.copy()
    expected[:2, :2] *= 2
    expected[:2, 2] = (expected[:2, 2] + 0.5) * 2 - 0.5
    np.testing.assert_allclose(K, expected)
    for name in ("cam0", "cam1"):
        _write_video(tmp_path / f"{name}.mp4", 5, (64, 48), fps=25.0)
    files = [str(tmp_path / "cam0.mp4"), str(tmp_path / "cam1.mp4")]
    assert main(["import-calibration", str(toml), *files, "--tracks", str(tracks), "--out", str(tmp_path / "w2")]) == 0
    assert "--tracks and --size only serve videos that are not here" in caplog.text
