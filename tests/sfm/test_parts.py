"""Pieces of `register`: frame choice, pairs, masks, intrinsics, PLY, crash isolation, evaluation."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from dynrecon.errors import InputError
from sfm.cameras import CameraSet, FrameCamera, VideoCameras
from sfm.evaluate import compare
from sfm.export import colmap_params, opencv_intrinsics, read_ply, write_ply
from sfm.frames import Resize, image_name, select_frames, sfm_folder
from sfm.isolated import ColmapCrashError, run_isolated
from sfm.masks import check_mask_folder, mask_from_points, user_mask
from sfm.pairs import build_pairs
from sfm.video import ProbedVideo


def _info(times: np.ndarray) -> ProbedVideo:
    return ProbedVideo(path=Path("v.mp4"), name="v", width=1920, height=1080, times=times, nominal_fps=30.0)


def test_select_frames() -> None:
    info = _info(np.arange(100) / 30.0)
    assert select_frames(info, step=10, max_frames=0).tolist() == list(range(0, 100, 10))
    assert select_frames(info, time_step=1.0, max_frames=0).tolist() == [0, 30, 60, 90]
    thinned = select_frames(info, max_frames=5)
    assert thinned.tolist() == [0, 25, 50, 74, 99]
    variable = _info(np.array([0.0, 0.01, 0.5, 0.52, 1.0, 1.6]))  # decoder timestamps, not frame counts
    assert select_frames(variable, time_step=0.5, max_frames=0).tolist() == [0, 2, 4, 5]


def test_sfm_image_names_have_no_whitespace() -> None:
    """COLMAP's pair lists split image names at spaces: phone file names ("WhatsApp Video 1.mp4") are encoded in
    the SfM folders, one to one (`%` encoded too), and plain names are unchanged."""
    names = ["cam0", "WhatsApp Video 1", "WhatsApp%20Video 1", "tab\there", "50 %"]
    folders = [sfm_folder(n) for n in names]
    assert folders[0] == "cam0" and len(set(folders)) == len(names)
    assert not any(c.isspace() for f in folders for c in f)
    assert image_name("WhatsApp Video 1", 7) == "WhatsApp%20Video%201/000007.jpg"


def test_build_pairs() -> None:
    names = {"a": [f"a/{i}" for i in range(6)], "b": [f"b/{i}" for i in range(4)]}
    pairs = build_pairs(names, overlap=2, keyframes=2)
    within = [p for p in pairs if p[0][0] == p[1][0]]
    across = [p for p in pairs if p[0][0] != p[1][0]]
    assert len(within) == (5 + 4) + (3 + 2)
    assert sorted(across) == [("a/0", "b/0"), ("a/0", "b/3"), ("a/5", "b/0"), ("a/5", "b/3")]
    assert len(set(pairs)) == len(pairs)


def test_intrinsics_conversion_round_trip() -> None:
    """OpenCV (original px) -> COLMAP (resized, +0.5 convention) -> OpenCV gives back the same K and dist."""
    resize = Resize(scale=0.5, width=960, height=540)
    K = np.array([[1500.0, 0.0, 955.3], [0.0, 1490.0, 541.2], [0.0, 0.0, 1.0]])
    dist = np.array([-0.1, 0.05, 0.001, -0.002])
    model, params = colmap_params(K, dist, resize)
    camera = pycolmap.Camera(model=model, width=960, height=540, params=params)
    K2, dist2 = opencv_intrinsics(camera, resize)
    np.testing.assert_allclose(K2, K, atol=1e-9)
    np.testing.assert_allclose(dist2, dist)
    # The same 3D point lands on the same pixel, up to the resize, in both conventions.
    point = np.array([[0.3, -0.2, 2.0]])
    colmap_px = camera.img_from_cam(point)[0]
    import cv2

    opencv_px = cv2.projectPoints(point, np.zeros(3), np.zeros(3), K, dist)[0].ravel()
    np.testing.assert_allclose(colmap_px, (opencv_px + 0.5) * 0.5, atol=1e-9)
    simple = pycolmap.Camera(model="SIMPLE_RADIAL", width=960, height=540, params=[700.0, 480.0, 270.0, 0.01])
    K3, dist3 = opencv_intrinsics(simple, resize)
    np.testing.assert_allclose(K3, [[1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 1]])
    np.testing.assert_allclose(dist3, [0.01, 0, 0, 0])


def test_opencvs_rational_model_converts_both_ways_and_projects_alike() -> None:
    """Eight coefficients (OpenCV's CALIB_RATIONAL_MODEL, which multiview_calib writes) are COLMAP's FULL_OPENCV in
    the same order; dynrecon's own projection (the recording's) and its rays agree with OpenCV's."""
    import cv2

    from reconstruct.outputs.recording_parts import project
    from reconstruct.solver.rays import normalized_image_points

    resize = Resize(scale=0.5, width=960, height=540)
    K = np.array([[1500.0, 0.0, 955.3], [0.0, 1490.0, 541.2], [0.0, 0.0, 1.0]])
    dist = np.array([2.1, 1.3, 0.001, -0.002, 0.05, 2.3, 1.9, 0.2])  # rational: large k1 and k4 cancel
    model, params = colmap_params(K, dist, resize)
    assert model == "FULL_OPENCV"
    camera = pycolmap.Camera(model=model, width=960, height=540, params=params)
    K2, dist2 = opencv_intrinsics(camera, resize)
    np.testing.assert_allclose(K2, K, atol=1e-9)
    np.testing.assert_allclose(dist2, dist)
    points = np.array([[0.3, -0.2, 2.0], [-0.5, 0.25, 1.5], [0.05, 0.02, 3.0]])
    opencv_px = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(camera.img_from_cam(points), (opencv_px + 0.5) * 0.5, atol=1e-7)
    ours, in_front = project(points[None], K[None], np.eye(3)[None], np.zeros((1, 3)), dist[None])
    assert in_front.all()
    np.testing.assert_allclose(ours[0], opencv_px, atol=1e-7)
    np.testing.assert_allclose(normalized_image_points(opencv_px, K, dist), points[:, :2] / points[:, 2:], atol=1e-6)


def test_user_masks_are_checked(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="masks folder not found"):
        check_mask_folder(tmp_path / "nonexist", ["cam0"])
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "camX.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(InputError, match="holds no mask of the videos cam0, cam1"):
        check_mask_folder(tmp_path / "masks", ["cam0", "cam1"])
    cv2.imwrite(str(tmp_path / "masks" / "cam0.png"), np.zeros((10, 10), np.uint8))
    check_mask_folder(tmp_path / "masks", ["cam0", "cam1"])
    resize = Resize(scale=0.5, width=200, height=100)
    with pytest.raises(InputError, match=r"cam0\.png: the mask is 10x10, another shape than its video's 200x100"):
        user_mask(tmp_path / "masks", "cam0", 3, resize)
    cv2.imwrite(str(tmp_path / "masks" / "cam0.png"), np.full((200, 400), 255, np.uint8))
    assert user_mask(tmp_path / "masks", "cam0", 3, resize).shape == (100, 200)
    assert user_mask(tmp_path / "masks", "cam1", 3, resize) is None


def test_mask_from_points() -> None:
    resize = Resize(scale=0.5, width=200, height=100)
    mask = mask_from_points(np.array([[100.0, 50.0], [300.0, 50.0], [200.0, 150.0]]), resize, radius=20)
    assert mask.shape == (100, 200)
    assert mask[50, 100] == 0  # inside the hull (original (200, 100))
    assert mask[25, 50] == 0 and mask[25, 41] == 0  # within 20 px (10 px resized) of a point
    assert mask[25, 30] == 255  # 40 px away
    assert mask[5, 5] == 255 and mask[95, 195] == 255


def test_ply_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3))
    rgb = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    write_ply(tmp_path / "b.ply", xyz, rgb)
    xyz2, rgb2 = read_ply(tmp_path / "b.ply")
    np.testing.assert_allclose(xyz2, xyz, atol=1e-6)
    np.testing.assert_array_equal(rgb2, rgb)
    assert (tmp_path / "b.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")


def test_isolated_stage_turns_abort_into_error(tmp_path: Path) -> None:
    log = tmp_path / "colmap.log"
    assert run_isolated("dumps", json.dumps, {"obj": [1, 2, 3]}, log) == "[1, 2, 3]"
    with pytest.raises(ColmapCrashError, match="killed by signal SIGABRT"):
        run_isolated("abort", os.abort, {}, log)
    with pytest.raises(ColmapCrashError, match="JSONDecodeError"):
        run_isolated("bad", json.loads, {"s": "nope"}, log)
    assert "===== dynrecon stage: abort =====" in log.read_text()


def test_an_isolated_stage_ends_with_its_caller(tmp_path: Path) -> None:
    """A caller killed outright (SIGKILL, a Dask nanny ending its worker) takes the stage's process with it."""
    code = "import signal, sys; from pathlib import Path; from sfm.isolated import run_isolated; "
    code += "run_isolated('pause', signal.pause, {}, Path(sys.argv[1]))"
    repo = Path(__file__).resolve().parents[2]
    caller = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "colmap.log")], cwd=repo)
    children = Path(f"/proc/{caller.pid}/task/{caller.pid}/children")
    deadline = time.monotonic() + 60
    while not children.read_text().split() and time.monotonic() < deadline:
        time.sleep(0.1)
    stage = int(children.read_text().split()[0])
    time.sleep(1.0)  # the stage has imported what it needs and waits
    assert Path(f"/proc/{stage}").exists()
    caller.kill()
    caller.wait(timeout=10)
    deadline = time.monotonic() + 10
    while _alive(stage) and time.monotonic() < deadline:
        time.sleep(0.1)
    orphaned = _alive(stage)
    if orphaned:  # the failure this test is about: do not leave it waiting for ever
        os.kill(stage, signal.SIGKILL)
    assert not orphaned


def _alive(pid: int) -> bool:
    """Running, not a zombie (an orphan is reaped by init, a zombie of ours by nobody until the test ends)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


def test_compare_recovers_similarity() -> None:
    rng = np.random.default_rng(1)
    truth, moved = CameraSet(), CameraSet()
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    A = q if np.linalg.det(q) > 0 else -q
    scale, shift = 2.5, np.array([1.0, -2.0, 0.5])
    for name in ("a", "b"):
        frames, frames_moved = [], []
        for i in range(4):
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            R = q if np.linalg.det(q) > 0 else -q
            center = rng.normal(size=3)
            frames.append(FrameCamera(frame=i, K=np.eye(3), R=R, t=-R @ center))
            # The same camera in a world with X' = scale A X + shift.
            R2 = R @ A.T
            frames_moved.append(FrameCamera(frame=i, K=np.eye(3), R=R2, t=-R2 @ (scale * A @ center + shift)))
        truth.videos.append(VideoCameras(name=name, width=10, height=10, frames=frames))
        moved.videos.append(VideoCameras(name=name, width=10, height=10, frames=frames_moved))
    result = compare(moved, truth)
    assert result.center_errors.max() < 1e-9 and result.rotation_errors_deg.max() < 1e-5
    assert abs(result.scale - 1 / scale) < 1e-9


def test_known_intrinsics_from_toml_and_cameras_json(tmp_path: Path) -> None:
    from sfm.calibration import StaticCamera, write_toml
    from sfm.cameras import write_cameras
    from sfm.intrinsics import known_intrinsics

    K = np.array([[900.0, 0.0, 640.0], [0.0, 905.0, 360.0], [0.0, 0.0, 1.0]])
    dist = np.array([0.1, -0.01, 0.0, 0.0])
    infos = [
        ProbedVideo(path=Path(f"{n}.mp4"), name=n, width=1280, height=720, times=np.zeros(1), nominal_fps=None)
        for n in ("cam_1", "cam_2")
    ]
    toml = write_toml(
        tmp_path / "c.toml",
        [
            StaticCamera(
                name=f"cam{i}",
                width=1280,
                height=720,
                K=K * [[1 + i, 1, 1], [1, 1 + i, 1], [1, 1, 1]],
                dist=dist,
                R=np.eye(3),
                t=np.zeros(3),
            )
            for i in (1, 2)
        ],
    )
    from_toml = known_intrinsics(toml, infos)
    assert from_toml["cam_2"][0][0, 0] == 2700.0 and from_toml["cam_1"][1] is not None
    cameras = CameraSet(
        videos=[
            VideoCameras(
                name="cam_2",
                width=1280,
                height=720,
                frames=[FrameCamera(frame=0, K=K, R=np.eye(3), t=np.zeros(3), dist=dist)],
            )
        ]
    )
    write_cameras(tmp_path / "cameras.json", cameras)
    from_json = known_intrinsics(tmp_path / "cameras.json", infos)
    assert list(from_json) == ["cam_2"] and np.allclose(from_json["cam_2"][0], K)
    # a named camera calibrated on another image (its principal point outside the video) is estimated instead,
    # as the warning says, not "none of the videos is in this file"
    small = [replace(info, width=480, height=360) for info in infos]
    assert known_intrinsics(tmp_path / "cameras.json", small) == {}
    with pytest.raises(InputError, match="none of the videos"):
        known_intrinsics(tmp_path / "cameras.json", [replace(infos[0], name="other")])


def test_wanted_frames_follow_tracks() -> None:
    from sfm.stage import Localize, _wanted_frames
    from tracking.tracks import Tracks

    info = _info(np.arange(50) / 30.0)
    tracks = Tracks.from_rows([("v", 7, "p", 1.0, 2.0), ("v", 31, "p", 1.0, 2.0), ("w", 3, "p", 0.0, 0.0)])
    sfm = np.array([0, 10, 20])
    assert _wanted_frames(info, sfm, tracks, Localize.AUTO).tolist() == [0, 7, 10, 20, 31]
    assert _wanted_frames(info, sfm, None, Localize.AUTO).tolist() == list(range(50))
    assert _wanted_frames(info, sfm, tracks, Localize.NONE).tolist() == [0, 10, 20]


def test_frame_rate_follows_the_contract() -> None:
    """cameras.json `fps`: the container's nominal rate, null when the decoder's timestamps are irregular."""
    assert _info(np.arange(10) / 30.0).fps == 30.0
    irregular = _info(np.array([0.0, 0.033, 0.070, 0.100, 0.150, 0.166]))
    assert irregular.variable_frame_rate and irregular.fps is None
    # Matroska's millisecond times of a constant 60 fps (16 and 17 ms steps): constant, the nominal rate kept
    milliseconds = dataclasses.replace(_info(np.round(np.arange(100) / 60.0, 3)), nominal_fps=60.0)
    assert not milliseconds.variable_frame_rate and milliseconds.fps == 60.0
    dropped = _info(np.round(np.delete(np.arange(101), 50) / 60.0, 3))  # one frame lost: variable
    assert dropped.variable_frame_rate and dropped.fps is None


def test_public_front_is_lazy() -> None:
    """`import sfm` and the CLI's parser load neither pycolmap nor OpenCV; the front names the stages."""
    code = (
        "import argparse, sys, sfm, sfm.cli\n"
        "sfm.cli.add_commands(argparse.ArgumentParser().add_subparsers())\n"
        "print([m for m in ('pycolmap', 'cv2', 'numpy', 'sfm.stage', 'sfm.calibration') if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"

    import sfm
    from sfm import calibration, cameras, options, stage

    assert sfm.register is stage.run and sfm.import_calibration is calibration.run
    assert sfm.RegisterOptions is options.RegisterOptions and sfm.read_cameras is cameras.read_cameras
    assert all(hasattr(sfm, name) for name in sfm.__all__)
    with pytest.raises(AttributeError):
        _ = sfm.no_such_name


def test_a_background_model_without_points_is_not_kept() -> None:
    """A handheld pan gave 4 models and kept one of 13 images and 0 points: every frame localized against it failed,
    and the 13 images' poses rested on nothing, exit 0. Models under MIN_MODEL_POINTS points are not kept."""
    from sfm.plan_io import StepNotes
    from sfm.stage import MIN_MODEL_POINTS, _largest_model

    models = {"0": 2, "1": 3, "2": 3, "3": 13}
    notes = StepNotes()
    assert _largest_model(models, notes, {"0": 40, "1": 500, "2": 90, "3": 0}) == "1"
    assert any("3 (13 images, 0 points)" in w and f"under {MIN_MODEL_POINTS}" in w for w in notes.warnings)
    none = StepNotes()
    assert _largest_model({"0": 13}, none, {"0": 5}) is None
    assert any("found no model" in w for w in none.warnings)
    assert _largest_model(models, StepNotes()) == "3"  # without point counts: the most images, as before
