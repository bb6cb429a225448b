"""`dynrecon register` end to end on the synthetic room (ground truth known), and its failure modes."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from sfm.cameras import CameraSet, read_cameras
from sfm.evaluate import compare
from sfm.export import read_ply
from sfm.report import posed_frames
from sfm.synthetic.demo import render_demo, sphere_tracks, three_cameras
from sfm.synthetic.room import Room
from sfm.video import probe_video, read_frames
from tracking.tracks import write_tracks

ROOM_DIAGONAL = float(np.linalg.norm(Room(textures=[np.zeros((1, 1, 3), np.uint8)] * 6).size))


@pytest.mark.slow
def test_register_synthetic_room(tmp_path: Path) -> None:
    """3 moving cameras (30/24/18 fps, different focal lengths), 4 moving spheres masked via tracks.csv."""
    videos = render_demo(tmp_path / "videos", three_cameras(480, 360, frames=(10, 8, 6)))
    truth = CameraSet(videos=[v.cameras for v in videos])
    ws = tmp_path / "ws"
    write_tracks(ws / "tracks.csv", sphere_tracks(videos))
    args = [
        "register",
        *(str(v.path) for v in videos),
        "--out",
        str(ws),
        "--long-side",
        "480",
        "--max-frames",
        "6",
        "--max-features",
        "1500",
        "--mask-radius",
        "70",
        # One thread makes COLMAP deterministic (random_seed is fixed); with threads this small scene's errors vary.
        "--threads",
        "1",
        # known clock offsets (a clap): no subject path here, so cameras.json carries them for the solve to test
        "--offsets",
        "cam0=0,cam2=-0.25",
    ]
    assert main(args) == 0

    cameras = read_cameras(ws / "cameras.json")
    assert [cameras.video(n).clock_offset for n in ("cam0", "cam1", "cam2")] == [0.0, None, -0.25]
    for video in truth.videos:
        assert cameras.video(video.name).frame_numbers().tolist() == video.frame_numbers().tolist()
        np.testing.assert_allclose(
            [f.time for f in cameras.video(video.name).frames], [f.time for f in video.frames], atol=1e-3
        )
    errors = compare(cameras, truth)
    assert len(errors.keys) == truth.num_frames == 24
    assert errors.center_errors.max() < 0.01 * ROOM_DIAGONAL
    assert errors.rotation_errors_deg.max() < 0.5
    for video in truth.videos:
        # Intrinsics in the original pixels and OpenCV's convention: cx, cy = (w - 1) / 2, (h - 1) / 2 here.
        # COLMAP's multithreaded runs differ slightly: focal ratios of 0.973-0.997 were seen over repeated runs
        # of this 6-frames-per-video scene (the poses stayed within the bounds above).
        K = cameras.video(video.name).frames[0].K
        assert abs(K[0, 0] / video.frames[0].K[0, 0] - 1) < 0.04
        assert abs(K[0, 2] - 239.5) < 3 and abs(K[1, 2] - 179.5) < 3

    report = json.loads((ws / "register_report.json").read_text())
    assert report["ok"] and set(report["timings_s"]) >= {"extract", "match", "map", "localize"}
    for entry in report["videos"]:
        assert entry["registered"] == entry["frames_given"] and entry["failed"] == []
        assert entry["registered_by_sfm"] == 6 and entry["mean_reprojection_error_px"] < 1.5
    xyz, rgb = read_ply(ws / "background.ply")
    assert len(xyz) == report["model"]["points"] > 1000 and rgb.shape == (len(xyz), 3)
    assert (ws / "sfm" / "database.db").exists() and (ws / "sfm" / "colmap.log").stat().st_size > 0
    assert len(list((ws / "sfm" / "masks" / "cam0").glob("*.png"))) == 10
    # JPEGs of the 6 SfM frames; tracked in-between frames are never written, SIFT fallbacks are.
    cam0 = next(v for v in report["videos"] if v["name"] == "cam0")
    sift = sum(1 for p in posed_frames(cam0).values() if p["path"] == "sift")
    assert len(list((ws / "frames" / "cam0").glob("*.jpg"))) == 6 + sift


def _flat_video(path: Path, frames: int = 6) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), 10.0, (96, 64))
    level = 80 + sum(path.stem.encode()) % 32  # another grey per name: identical files are refused as one video
    for _ in range(frames):
        writer.write(np.full((64, 96, 3), level, np.uint8))
    writer.release()
    return path


def test_untextured_videos_fail_clearly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    videos = [str(_flat_video(tmp_path / f"flat{i}.mp4")) for i in range(2)]
    assert main(["register", *videos, "--out", str(tmp_path / "ws"), "--max-frames", "3"]) == 2
    err = capsys.readouterr().err
    assert "dynrecon register: error:" in err and "cameras.json not written" in err and "try more overlap" in err
    report = json.loads((tmp_path / "ws" / "register_report.json").read_text())
    assert not report["ok"] and any("SIFT features" in w for w in report["warnings"])
    assert all(
        "no SfM image of it has 50 SIFT features" in run["reason"] for v in report["videos"] for run in v["failed"]
    )
    assert not (tmp_path / "ws" / "cameras.json").exists()


def test_a_failed_run_keeps_the_last_results(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ws = tmp_path / "ws"
    ws.mkdir()
    last = {"cameras.json": '{"videos": []}', "background.ply": "ply", "register_report.json": '{"ok": true}'}
    for name, text in last.items():
        (ws / name).write_text(text)
    videos = [str(_flat_video(tmp_path / f"flat{i}.mp4")) for i in range(2)]
    for _ in range(2):  # a second failure keeps them too
        assert main(["register", *videos, "--out", str(ws), "--max-frames", "3"]) == 2
        err = capsys.readouterr().err
        assert f"the last successful run's cameras.json is kept in {ws / 'previous'}" in err
        assert {name: (ws / "previous" / name).read_text() for name in last} == last
        assert not (ws / "cameras.json").exists() and not json.loads((ws / "register_report.json").read_text())["ok"]


def test_bad_video_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    video = _flat_video(tmp_path / "a.mp4", frames=2)
    (tmp_path / "b").mkdir()
    _flat_video(tmp_path / "b" / "a.mp4", frames=2)
    assert main(["register", str(video), "--out", str(tmp_path / "ws")]) == 2
    assert "at least two videos" in capsys.readouterr().err
    assert main(["register", str(video), str(tmp_path / "b" / "a.mp4"), "--out", str(tmp_path / "ws")]) == 2
    assert "'a' is used twice" in capsys.readouterr().err
    assert main(["register", str(video), str(tmp_path / "b"), "--out", str(tmp_path / "ws")]) == 2
    assert "is a directory" in capsys.readouterr().err
    frames = tmp_path / "frames"  # a phone app's or a camera's frame sequence
    frames.mkdir()
    cv2.imwrite(str(frames / "00001.jpg"), np.zeros((8, 8, 3), np.uint8))
    assert main(["register", str(video), str(frames), "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err
    assert "it holds images: a frame sequence?" in err and f"ffmpeg -framerate 30 -i {frames}/%05d.jpg" in err
    other = _flat_video(tmp_path / "c.mp4", frames=2)
    two = ["register", str(video), str(other), "--out", str(tmp_path / "ws")]
    assert main([*two, "--offsets", "a=0,d=0.1"]) == 2
    assert "--offsets names video 'd', which is not among the videos (a, c)" in capsys.readouterr().err
    assert main([*two, "--offsets", "a=0", "--synchronized"]) == 2
    assert "--synchronized and --offsets both given" in capsys.readouterr().err
    assert not (tmp_path / "ws" / "register_report.json").exists()  # refused before any work


def test_an_unreadable_video_is_left_out_and_the_others_go_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    videos = [str(_flat_video(tmp_path / f"flat{i}.mp4")) for i in range(2)]
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00not a video" * 100)
    # the two readable (flat) videos are still registered (and fail for their own reason: no texture)
    assert main(["register", *videos, str(broken), "--out", str(tmp_path / "ws"), "--max-frames", "3"]) == 2
    err = capsys.readouterr().err
    assert "try more overlap" in err
    report = json.loads((tmp_path / "ws" / "register_report.json").read_text())
    assert any(w.startswith("left out: ") and "broken.mp4" in w for w in report["warnings"])
    assert [v["name"] for v in report["videos"]] == ["flat0", "flat1"]
    assert [u["path"] for u in report["unreadable_videos"]] == [str(broken)]
    assert "cannot open" in report["unreadable_videos"][0]["reason"]
    # every warning of the report is on the console too (several are only written there), once more at the end
    logged = [r.getMessage() for r in caplog.records if r.name == "sfm.stage"]
    assert len(report["warnings"]) == 4 and logged[-4:] == report["warnings"]
    # with one readable video left there is nothing to register: the unreadable one's reason is the error
    assert main(["register", videos[0], str(broken), "--out", str(tmp_path / "ws2")]) == 2
    assert "broken.mp4" in capsys.readouterr().err


LOSSLESS = ["-c:v", "libx264", "-qp", "0", "-pix_fmt", "yuv420p", "-threads", "1"]


def _ffmpeg(*args: str | Path) -> None:
    ffmpeg = shutil.which("ffmpeg")
    assert ffmpeg is not None
    subprocess.run([ffmpeg, "-hide_banner", "-loglevel", "error", "-y", *map(str, args)], check=True)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="needs ffmpeg (Debian package) to write the rotated video")
def test_a_rotated_video_registers_as_the_same_video_stored_upright(tmp_path: Path) -> None:
    """A phone's portrait video is stored landscape with a 90-degree display rotation: registration must give the
    same cameras (poses, intrinsics, image size) as for the same video stored upright."""
    videos = render_demo(tmp_path / "videos", three_cameras(480, 360, frames=(8, 6, 6)))
    sets = {"upright": tmp_path / "upright", "rotated": tmp_path / "rotated"}
    for folder in sets.values():
        folder.mkdir()
        for video in videos[1:]:
            shutil.copy(video.path, folder / video.path.name)
    source = videos[0].path
    # The same decoded pixels both ways: lossless, and turned clockwise + flagged to be shown turned back.
    _ffmpeg("-i", source, *LOSSLESS, sets["upright"] / "cam0.mp4")
    turned = tmp_path / "turned.mp4"
    _ffmpeg("-i", source, "-vf", "transpose=1", *LOSSLESS, turned)
    _ffmpeg("-i", turned, "-c", "copy", "-metadata:s:v:0", "rotate=90", sets["rotated"] / "cam0.mp4")
    found = {}
    for name, folder in sets.items():
        ws = tmp_path / f"ws_{name}"
        paths = [str(folder / f"cam{i}.mp4") for i in range(3)]
        options = ["--long-side", "480", "--max-frames", "6", "--max-features", "1500", "--threads", "1"]
        assert main(["register", *paths, "--out", str(ws), *options]) == 0
        found[name] = read_cameras(ws / "cameras.json")
    for upright, rotated in zip(found["upright"].videos, found["rotated"].videos, strict=True):
        assert (rotated.name, rotated.width, rotated.height) == (upright.name, upright.width, upright.height)
        assert rotated.frame_numbers().tolist() == upright.frame_numbers().tolist()
        for a, b in zip(upright.frames, rotated.frames, strict=True):
            np.testing.assert_allclose(b.K, a.K, atol=1e-6)
            np.testing.assert_allclose(b.R, a.R, atol=1e-6)
            np.testing.assert_allclose(b.t, a.t, atol=1e-6)


@pytest.mark.slow
def test_a_camera_that_never_sees_the_background_is_reported_and_the_others_register(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the room's three cameras, and a fourth filming another (textured) wall that shares nothing with the room
    videos = render_demo(tmp_path / "videos", three_cameras(480, 360, frames=(10, 8, 6)))
    elsewhere = tmp_path / "videos" / "elsewhere.mp4"
    rng = np.random.default_rng(5)
    wall = cv2.GaussianBlur(rng.integers(0, 255, (400, 560, 3), dtype=np.uint8), (5, 5), 0)
    writer = cv2.VideoWriter(str(elsewhere), cv2.VideoWriter.fourcc(*"mp4v"), 10.0, (480, 360))
    for i in range(8):
        writer.write(np.ascontiguousarray(wall[i * 4 : i * 4 + 360, i * 8 : i * 8 + 480]))
    writer.release()
    ws = tmp_path / "ws"
    write_tracks(ws / "tracks.csv", sphere_tracks(videos))
    paths = [*(str(v.path) for v in videos), str(elsewhere)]
    args = ["register", *paths, "--out", str(ws), "--long-side", "480", "--max-frames", "6", "--threads", "1"]
    assert main([*args, "--max-features", "1500", "--mask-radius", "70"]) == 0
    cameras = read_cameras(ws / "cameras.json")
    assert sorted(v.name for v in cameras.videos) == ["cam0", "cam1", "cam2"]
    report = json.loads((ws / "register_report.json").read_text())
    alone = next(v for v in report["videos"] if v["name"] == "elsewhere")
    assert alone["posed_by"] == "none" and alone["registered"] == 0
    assert alone["failed"] and all(f["reason"] for f in alone["failed"])
    assert all(v["registered"] == v["frames_in_video"] for v in report["videos"] if v["name"] != "elsewhere")
    captured = capsys.readouterr()
    said = [line for line in (captured.out + captured.err).splitlines() if "elsewhere" in line and "%" not in line]
    assert said == [  # its 6 SfM frames of 8: it has no tracks to ask for the others
        "elsewhere: 0/6 frames registered of 8 in the video (--localize all poses the others) (moving camera; "
        "posed by none; video not in the kept model)"
    ]
    assert alone["failed"][0]["reason"] == "video not in the kept model"


@pytest.mark.slow
def test_frames_without_texture_are_reported_and_the_rest_register(tmp_path: Path) -> None:
    # cam0's last 3 of 10 frames are a flat grey (a hand over the lens): those fail with a reason, the rest register
    videos = render_demo(tmp_path / "videos", three_cameras(480, 360, frames=(10, 8, 6)))
    covered = tmp_path / "videos" / "covered.mp4"
    info = probe_video(videos[0].path)
    writer = cv2.VideoWriter(str(covered), cv2.VideoWriter.fourcc(*"mp4v"), 30.0, (info.width, info.height))
    for frame, image in read_frames(info.path, np.arange(info.num_frames)):
        writer.write(np.full_like(image, 90) if frame >= 7 else image)
    writer.release()
    ws = tmp_path / "ws"
    paths = [str(covered), *(str(v.path) for v in videos[1:])]
    args = ["register", *paths, "--out", str(ws), "--long-side", "480", "--max-frames", "6", "--threads", "1"]
    assert main([*args, "--max-features", "1500"]) == 0
    report = json.loads((ws / "register_report.json").read_text())
    video = next(v for v in report["videos"] if v["name"] == "covered")
    failed = {f: run["reason"] for run in video["failed"] for f in range(run["first"], run["last"] + 1)}
    assert sum(run["frames"] for run in video["failed"]) == len(failed)  # the runs hold no posed frame
    posed = set(posed_frames(video))
    assert {7, 8, 9} <= set(failed) and all("SIFT: no features" in failed[f] for f in (7, 8, 9))
    few = [w for w in report["warnings"] if w.startswith("covered: ") and "untextured or blurred" in w]
    assert len(few) == 1 and "covered/000007.jpg" in few[0]  # one line per video, naming the images
    assert set(range(7)) <= posed
    cameras = read_cameras(ws / "cameras.json")
    assert set(cameras.video("covered").frame_numbers().tolist()) == posed


def test_a_background_pose_no_camera_has_is_left_unposed_and_said() -> None:
    """A degenerate model (a board-only scene's gave k1 = 1452) would make cameras.json refuse itself with no
    report: such frames are left unposed, with one warning per video naming the value."""
    import pycolmap

    from sfm.plan import FramePose
    from sfm.stage import _drop_implausible

    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    good = FramePose(pose=pycolmap.Rigid3d(), source="sfm", intrinsics=(K, np.array([0.1, 0, 0, 0])))
    bad = FramePose(pose=pycolmap.Rigid3d(), source="sfm", intrinsics=(K, np.array([1452.3, 0, 0, 0])))
    results = {"a": {0: good, 1: good}, "b": {0: bad, 1: good}}
    warnings: list[str] = []
    _drop_implausible(results, warnings)
    assert results["a"][0].pose is not None and results["b"][1].pose is not None
    assert results["b"][0].pose is None and "no camera's" in (results["b"][0].reason or "")
    assert len(warnings) == 1 and warnings[0].startswith("b: 1 frame(s)") and "1452.3" in warnings[0]


def test_a_background_pose_with_no_lens_focal_is_not_used() -> None:
    """A background model of a head-worn camera and two GoPros (EgoHumans' badminton clips, one at 5 fps) posed the
    GoPros with focals of 62 and 81 px for 910 px wide images (fields of view near 165 degrees) and exited 0 without
    a word, the head-worn camera's path 23 degrees off: such poses are dropped (each frame says why), and the videos
    the same model still poses are named in a warning. Without the subject's tracks too."""
    import pycolmap

    from sfm.frames import Resize
    from sfm.plan import FramePose, VideoPlan
    from sfm.stage import _drop_no_lens
    from sfm.video import ProbedVideo

    def plan(name: str, width: int, height: int, static: bool) -> VideoPlan:
        info = ProbedVideo(
            path=Path(f"{name}.mp4"), name=name, width=width, height=height, times=np.arange(3) / 10, nominal_fps=10
        )
        resize = Resize(scale=1.0, width=width, height=height)
        return VideoPlan(info=info, resize=resize, sfm_frames=np.zeros(0, np.int64), wanted=np.arange(3), static=static)

    def posed(focal: float, cx: float, source: str = "sfm") -> dict[int, FramePose]:
        K = np.array([[focal, 0, cx], [0, focal, 256.0], [0, 0, 1]])
        return {f: FramePose(pose=pycolmap.Rigid3d(), source=source, intrinsics=(K, None)) for f in range(3)}

    plans = [plan("cam02", 910, 512, True), plan("cam14", 910, 512, True), plan("aria04", 512, 512, False)]
    results = {"cam02": posed(62.0, 455), "cam14": posed(433.0, 455), "aria04": posed(150.0, 256)}
    warnings: list[str] = []
    _drop_no_lens(plans, results, warnings)
    assert all(r.pose is None and "no lens" in (r.reason or "") for r in results["cam02"].values())
    assert all(r.pose is not None for name in ("cam14", "aria04") for r in results[name].values())
    assert warnings[0].startswith("cam02: the background's pose is not used: its intrinsics are no lens")
    assert warnings[1].startswith("cam14, aria04: posed by the same background model as cam02")
    untouched = {"cam02": posed(433.0, 455), "cam14": posed(433.0, 455), "aria04": posed(150.0, 256)}
    _drop_no_lens(plans, untouched, warnings := [])
    assert not warnings and all(r.pose is not None for frames in untouched.values() for r in frames.values())


def test_a_video_posed_in_part_says_how_many_frames() -> None:
    """A head-worn camera posed in 4 of its 27 frames was named "registered" in the failure, like a whole video."""
    import pycolmap

    from sfm.frames import Resize
    from sfm.plan import FramePose, VideoPlan
    from sfm.stage import _posed_share
    from sfm.video import ProbedVideo

    info = ProbedVideo(path=Path("aria.mp4"), name="aria", width=64, height=64, times=np.arange(3) / 5, nominal_fps=5)
    plan = VideoPlan(
        info=info, resize=Resize(scale=1.0, width=64, height=64), sfm_frames=np.zeros(0, np.int64), wanted=np.arange(3)
    )
    some = {0: FramePose(pose=pycolmap.Rigid3d()), 1: FramePose(pose=None), 2: FramePose(pose=None)}
    assert _posed_share(plan, some) == "aria: 1 of 3 frames"
    assert _posed_share(plan, {f: FramePose(pose=pycolmap.Rigid3d()) for f in range(3)}) == "aria"
