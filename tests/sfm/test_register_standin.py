"""`register --fps` without the videos (2D tracks shared without them, a drone's or a DLTdv user's detections):
each VIDEO that is no file is a name, its frames the tracks', taken as a static camera and posed from the
subject's tracks, against synthetic ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from sfm.calibration import StaticCamera, write_toml
from sfm.cameras import read_cameras
from sfm.evaluate import similarity
from sfm.subject.synthetic import Truth, make_rig
from tracking.tracks import Tracks, write_tracks

FPS = 30.0


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Truth]:
    """A skeleton filmed by 4 static cameras at 30 fps started at different times: tracks.csv and a calib.toml of
    their intrinsics (its poses are not read: --intrinsics takes K and the size only)."""
    folder = tmp_path_factory.mktemp("standin")
    tracks, _, truth = make_rig(kind="skeleton", n_cameras=4, duration=6.0, fps=(FPS,) * 5, distortion=False, seed=0)
    write_tracks(folder / "tracks.csv", tracks)
    cameras = [
        StaticCamera(name=n, width=1920, height=1080, K=K, dist=np.zeros(4), R=R, t=t)
        for n, K, R, t in zip(truth.names, truth.K, truth.R, truth.t, strict=True)
    ]
    write_toml(folder / "calib.toml", cameras)
    return folder, truth


def test_names_with_fps_are_posed_from_the_tracks(rig: tuple[Path, Truth], tmp_path: Path) -> None:
    folder, truth = rig
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "tracks.csv").write_bytes((folder / "tracks.csv").read_bytes())  # WS/tracks.csv, as after import-tracks
    args = ["register", *truth.names, "--out", str(ws), "--fps", str(FPS), "--intrinsics", str(folder / "calib.toml")]
    assert main(args) == 0
    report = json.loads((ws / "register_report.json").read_text())
    assert [(c["name"], c["posed"]) for c in report["subject"]["cameras"]] == [(n, True) for n in truth.names]
    assert [(v["name"], v["camera"], v["camera_set_by"], v["posed_by"]) for v in report["videos"]] == [
        (name, "static", "--fps", "subject") for name in truth.names
    ]
    videos = {v.name: v for v in read_cameras(ws / "cameras.json").videos}
    assert all((v.width, v.height, v.fps) == (1920, 1080, FPS) for v in videos.values())
    # --fps's rate, not measured times: the solve fits each one's true rate (tests/reconstruct/test_given_rates.py)
    assert all(f.time is None for v in videos.values() for f in v.frames)
    centres = np.array([-videos[n].frames[0].R.T @ videos[n].frames[0].t for n in truth.names])
    scale, R, t = similarity(centres, truth.centres())  # arbitrary units without --scale: one similarity
    spread = np.linalg.norm(truth.centres() - truth.centres().mean(0), axis=1).max()
    aligned = scale * centres @ R.T + t
    assert np.linalg.norm(aligned - truth.centres(), axis=1).max() < 0.02 * spread
    for name, R_true in zip(truth.names, truth.R, strict=True):
        turned = videos[name].frames[0].R @ R.T @ R_true.T
        assert np.degrees(np.arccos(np.clip((np.trace(turned) - 1) / 2, -1, 1))) < 1.0
    offsets = np.array([videos[n].clock_offset - videos[truth.names[0]].clock_offset for n in truth.names])
    np.testing.assert_allclose(offsets, np.array(truth.offsets[:4]) - truth.offsets[0], atol=1 / FPS)


@pytest.mark.parametrize(
    ("extra", "what"),
    [
        ([], "nothing gives its image size (give the videos' size with --size WIDTHxHEIGHT (or --intrinsics"),
        (["--size", "1920x1080", "--camera-motion", "moving"], "needs static cameras: not with --camera-motion moving"),
        (["--size", "1920x1080", "--subject", "never"], "not with --subject never"),
        (["--size", "640x480"], "tracks reach x, y = "),  # one --size for cameras of another size
    ],
)
def test_what_a_name_cannot_give_is_said_in_one_line(
    rig: tuple[Path, Truth], tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], what: str
) -> None:
    folder, truth = rig
    ws = tmp_path / "ws"
    args = ["register", *truth.names, "--out", str(ws), "--fps", str(FPS), "--tracks", str(folder / "tracks.csv")]
    assert main([*args, *extra]) == 2
    error = capsys.readouterr().err.splitlines()[-1]  # in this process, off a terminal, a bar's line may come first
    assert what in error and error.startswith("dynrecon register: error: "), error
    assert not (ws / "cameras.json").exists()


def test_a_name_the_tracks_lack_is_said(rig: tuple[Path, Truth], tmp_path: Path, capsys) -> None:
    folder, truth = rig
    args = ["register", *truth.names[:3], "cam9", "--out", str(tmp_path / "ws"), "--fps", str(FPS)]
    assert main([*args, "--tracks", str(folder / "tracks.csv"), "--size", "1920x1080"]) == 2
    error = capsys.readouterr().err
    assert "cam9: no such video, and" in error and "has no tracks of a video 'cam9'" in error, error


def test_rates_per_video(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Cameras at different rates (a drone filmed by phones at 25-60 fps): --fps NAME=FPS per video; a name without
    one, or a rate that is none, is said in one line."""
    from dynrecon.arguments import frame_rates
    from sfm.video_standin import stand_in_videos

    tracks = write_tracks(tmp_path / "t.csv", Tracks.from_rows([("a", 9, "p", 1.0, 2.0), ("b", 4, "p", 1.0, 2.0)]))
    rates = frame_rates("a=59.94, b=25")
    assert rates == {"a": 59.94, "b": 25.0} and frame_rates("30") == 30.0
    a, b = stand_in_videos(["a", "b"], tracks, rates)
    assert a is not None and b is not None and (a.num_frames, a.fps, b.num_frames, b.fps) == (10, 59.94, 5, 25.0)
    np.testing.assert_allclose(b.times, np.arange(5) / 25.0)
    with pytest.raises(InputError, match=r"--fps gives no rate for 'b' \(rates for: a\)"):
        stand_in_videos(["a", "b"], tracks, {"a": 30.0})
    for bad in ("0", "-30", "inf", "a=0", "a=x", "a=30,a=25", "=30", "fast"):
        with pytest.raises(argparse.ArgumentTypeError):
            frame_rates(bad)
    with pytest.raises(SystemExit):
        main(["register", "a", "b", "--out", str(tmp_path / "ws"), "--fps", "a=30,b"])
    assert "'b': give NAME=FPS once per video" in capsys.readouterr().err


def test_sizes_come_from_the_cameras_matched_over_every_video(tmp_path: Path) -> None:
    """A file beside two names, a calibration whose cameras are named otherwise (matched by order): each name gets
    its own camera's size, as the intrinsics match them over every video (not over the names alone)."""
    import dataclasses

    from sfm.stage import _size_stand_ins
    from sfm.video import probe_video
    from sfm.video_standin import stand_in_videos

    from .test_import_calibration import _random_cameras, _write_video

    cameras = _random_cameras(["left", "mid", "right"])
    cameras[1] = dataclasses.replace(cameras[1], width=80, height=60)
    cameras[2] = dataclasses.replace(cameras[2], width=100, height=50)
    toml = write_toml(tmp_path / "calib.toml", cameras)
    _write_video(tmp_path / "a.mp4", 5, (64, 48))
    rows = [(v, f, "p", 10.0, 20.0) for v in ("b", "c") for f in range(4)]
    tracks = write_tracks(tmp_path / "tracks.csv", Tracks.from_rows(rows))
    values = [str(tmp_path / "a.mp4"), "b", "c"]
    stand_ins = stand_in_videos(values, tracks, 30.0)
    infos = [stand_in or probe_video(Path(v)) for v, stand_in in zip(values, stand_ins, strict=True)]
    from sfm.options import RegisterOptions

    _size_stand_ins(infos, RegisterOptions(fps=30.0, intrinsics=toml))
    assert [(i.name, i.stand_in, i.width, i.height) for i in infos] == [
        ("a", False, 64, 48),
        ("b", True, 80, 60),
        ("c", True, 100, 50),
    ]


def test_a_path_that_is_no_file_is_a_typo_and_names_are_matched_as_the_tracks_spell_them(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from sfm.video_standin import stand_in_videos

    rows = [(v, f, "p", 10.0, 20.0) for v in ("Cam_0", "cam1") for f in range(3)]
    tracks = write_tracks(tmp_path / "tracks.csv", Tracks.from_rows(rows))
    for typo in ("videos/cam0.mp4", "cam0.mp4", str(tmp_path / "cam0")):
        with pytest.raises(InputError, match=r"no such video file \(check the path; a video that is not here is"):
            stand_in_videos([typo, "cam1"], tracks, 30.0)
    cam0, cam1 = stand_in_videos(["cam0", "cam1"], tracks, {"cam0.mp4": 50.0, "cam1": 25.0, "cam7": 30.0})
    assert cam0 is not None and cam1 is not None and (cam0.num_frames, cam0.fps, cam1.fps) == (3, 50.0, 25.0)
    assert "'Cam_0' taken as the video 'cam0'" in caplog.text
    assert "--fps cam7: no video given by that name is missing: ignored" in caplog.text


def test_a_bare_name_without_fps_says_how_to_use_one(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["register", "cam0", "cam1", "--out", str(tmp_path / "ws")]) == 2
    error = capsys.readouterr().err.splitlines()[-1]
    assert "cam0: no such video" in error and "give --fps" in error, error
