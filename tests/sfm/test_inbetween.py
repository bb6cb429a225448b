"""In-between frames posed by tracking the keyframes' features (`sfm.track_pose`), SIFT where tracking fails.

One small synthetic handheld capture (2 videos x 14 frames, 4 SfM frames each) is registered once; in cam0 one frame
is rendered with the camera turned away by a sudden pan, which optical flow cannot follow: that frame must come from
the SIFT path, every other in-between frame from tracking, and the report must say so per frame.

A camera that walks away from its only keyframe (controlled: the keyframe's 3D points are the rendered room's, the
poses are compared with the truth directly) loses the keyframe's features; tracking then promotes well-posed frames
to keyframes and poses the rest of the walk from their triangulated points.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

import sfm.track_pose
from dynrecon.cli import main
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras
from sfm.evaluate import compare
from sfm.frames import Resize
from sfm.report import posed_frames
from sfm.synthetic.demo import three_cameras
from sfm.synthetic.room import Room, _rays, render
from sfm.synthetic.scene import CameraPath
from sfm.track_pose import Seed, VideoTracking, segments, spread, track_video
from sfm.triangulate import triangulate

FRAMES = 14
JUMP = 6  # cam0's frame rendered with the sudden pan (not an SfM frame: those are 0, 4, 9, 13)
PAN_DEG = 40.0


def _render(room: Room, path: CameraPath, out: Path, jump: int | None) -> VideoCameras:
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter.fourcc(*"mp4v"), path.fps, (path.width, path.height))
    frames = []
    for index, time in enumerate(path.times()):
        R, t = path.pose(float(time))
        if index == jump:
            turn, _ = cv2.Rodrigues(np.array([0.0, np.radians(PAN_DEG), 0.0]))
            centre = -R.T @ t
            R = turn @ R
            t = -R @ centre
        image, _, _ = render(room, path.K, R, t, path.width, path.height)
        writer.write(image)
        frames.append(FrameCamera(frame=index, time=float(time), K=path.K.copy(), R=R, t=t))
    writer.release()
    return VideoCameras(name=path.name, width=path.width, height=path.height, fps=path.fps, frames=frames)


@pytest.fixture(scope="module")
def registered(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, CameraSet]:
    folder = tmp_path_factory.mktemp("inbetween")
    room = Room(seed=3)
    paths = three_cameras(400, 300, frames=(FRAMES, FRAMES, FRAMES), fps=(30.0, 30.0, 30.0))[:2]
    truth = CameraSet(
        videos=[_render(room, p, folder / f"{p.name}.mp4", JUMP if i == 0 else None) for i, p in enumerate(paths)]
    )
    ws = folder / "ws"
    args = ["register", *(str(folder / f"{p.name}.mp4") for p in paths), "--out", str(ws)]
    args += ["--max-frames", "4", "--max-features", "1500", "--threads", "1"]
    assert main(args) == 0
    return ws, truth


def test_tracked_poses_agree_with_truth(registered: tuple[Path, CameraSet]) -> None:
    ws, truth = registered
    errors = compare(read_cameras(ws / "cameras.json"), truth)
    assert len(errors.keys) == 2 * FRAMES
    # Metres in an 8 x 6 x 3 m room: every frame (10 of 14 per video tracked) within 2 cm and 0.2 degrees.
    assert errors.center_errors.max() < 0.02 and errors.rotation_errors_deg.max() < 0.2


def test_lost_frame_falls_back_to_sift_and_report_says_so(registered: tuple[Path, CameraSet]) -> None:
    ws, _ = registered
    report = json.loads((ws / "register_report.json").read_text())
    by_name = {v["name"]: v for v in report["videos"]}
    assert report["options"]["inbetween"] == "track"
    for name, video in by_name.items():
        paths = {f: p["path"] for f, p in sorted(posed_frames(video).items())}
        assert len(paths) == FRAMES and video["failed"] == []
        assert [f for f, p in paths.items() if p == "sfm"] == [0, 4, 9, 13]
        lost = [JUMP] if name == "cam0" else []
        assert [f for f, p in paths.items() if p == "sift"] == lost
        assert video["registered_by_tracking"] == FRAMES - 4 - len(lost)
        assert video["keyframes_added"] == 0  # the keyframes' features never thin out in 4 frames
        assert all(p["inliers"] >= 30 for p in posed_frames(video).values())


def test_segments_and_spread() -> None:
    parts = segments([3, 8], [0, 1, 5, 9])
    assert [(s.before, s.after, s.inner, s.needed) for s in parts] == [
        (None, 3, [0, 1, 2], [0, 1]),
        (3, 8, [4, 5, 6, 7], [5]),
        (8, None, [9], [9]),
    ]
    uv = np.concatenate([np.full((900, 2), 5.0), np.random.default_rng(0).uniform(0, 100, (100, 2))])
    chosen = spread(uv, np.ones(len(uv)), 100.0, 100.0, count=200)
    assert len(chosen) == 200 and (chosen >= 900).sum() >= 95  # a crowded corner does not take every slot


WALK_FRAMES = 30
WALK_SIZE = (320, 240)


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, VideoCameras, Seed, pycolmap.Camera]:
    """A camera walking 4 m along the room while its view sweeps 6 m across the far wall, so that the last frames
    see nothing of the first; frame 0's corners with their true 3D points (from the rendered depth) as its seed."""
    width, height = WALK_SIZE
    focal = 0.78 * width
    K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    path = CameraPath(
        name="walk",
        K=K,
        width=width,
        height=height,
        fps=30.0,
        num_frames=WALK_FRAMES,
        start=np.array([1.5, 0.8, 1.5]),
        end=np.array([5.5, 1.0, 1.6]),
        target_start=np.array([1.0, 6.0, 1.3]),
        target_end=np.array([7.0, 6.0, 1.5]),
    )
    room = Room(seed=3)
    video = tmp_path_factory.mktemp("walk") / "walk.mp4"
    truth = _render(room, path, video, None)
    R, t = truth.frames[0].R, truth.frames[0].t
    image, depth, _ = render(room, K, R, t, width, height)
    corners = cv2.goodFeaturesToTrack(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), 600, 0.01, 5)
    uv = np.round(np.asarray(corners).reshape(-1, 2)).astype(int)
    xyz = truth.frames[0].center + depth[uv[:, 1], uv[:, 0], None] * _rays(K, R, width, height)[uv[:, 1], uv[:, 0]]
    seed = Seed(frame=0, uv=uv.astype(float), xyz=xyz, weight=np.ones(len(uv)))
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=width, height=height, params=[focal, width / 2, height / 2])
    return video, truth, seed, camera


def _track_walk(walk: tuple[Path, VideoCameras, Seed, pycolmap.Camera]) -> tuple[VideoTracking, dict[int, np.ndarray]]:
    """Tracking of every frame from frame 0's seed; frame -> (centre error in metres, rotation error in degrees)."""
    video, truth, seed, camera = walk
    resize = Resize.for_video_size(*WALK_SIZE, 1280)
    result = track_video(video, {0: seed}, list(range(1, WALK_FRAMES)), camera, resize, lambda _: None, min_inliers=30)
    errors = {}
    for frame, posed in result.posed.items():
        pose = posed.located.cam_from_world
        assert pose is not None
        R = pose.rotation.matrix()
        true = truth.frames[frame]
        angle = np.degrees(np.arccos(np.clip((np.trace(R @ true.R.T) - 1) / 2, -1.0, 1.0)))
        errors[frame] = np.array([np.linalg.norm(-R.T @ np.asarray(pose.translation) - true.center), angle])
    return result, errors


def test_walk_away_from_the_keyframe_is_tracked_from_added_keyframes(
    walk: tuple[Path, VideoCameras, Seed, pycolmap.Camera], monkeypatch: pytest.MonkeyPatch
) -> None:
    with monkeypatch.context() as patch:  # before: a chain never promotes a frame
        patch.setattr(sfm.track_pose, "FRESH_SURVIVAL", -1.0)
        before, before_errors = _track_walk(walk)
    after, after_errors = _track_walk(walk)
    # Before, the last frames of the walk lost frame 0's features: they were left for SIFT.
    assert len(before.failed) >= 5 and max(before.posed) < WALK_FRAMES - 5 and not before.added
    # After, every frame is posed by tracking, through at least one added keyframe.
    assert sorted(after.posed) == list(range(1, WALK_FRAMES)) and not after.failed
    assert after.added and all(count >= 30 for count in after.added.values())
    beyond = np.array([e for f, e in after_errors.items() if f > min(after.added)])
    assert len(beyond) >= 10
    # Metres and degrees against the truth: the frames beyond the first added keyframe within 6 cm and 0.6 degrees
    # (the chain from frame 0 alone drifts to 2-3 cm and 0.3 degrees before it), and on the frames both posed, the
    # median no worse than before's (by 1.2x at most).
    assert beyond[:, 0].max() < 0.06 and beyond[:, 1].max() < 0.6
    common = sorted(before_errors)
    before_median = np.median([before_errors[f] for f in common], axis=0)
    after_median = np.median([after_errors[f] for f in common], axis=0)
    assert np.all(after_median <= 1.2 * before_median)


def test_triangulate_checks_angle_and_reprojection() -> None:
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=200, height=100, params=[100.0, 100.0, 50.0])
    first = pycolmap.Rigid3d()
    second = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-0.5, 0.0, 0.0]))  # centre 0.5 m to the right
    xyz = np.array([[0.2, 0.1, 4.0], [0.0, 0.0, 100.0], [-0.3, -0.1, 3.0]])  # the second too far: under 0.5 deg
    seen = [np.asarray(camera.img_from_cam(xyz @ p.rotation.matrix().T + p.translation)) for p in (first, second)]
    seen[1][2] += 5.0  # the third mismatched by 5 pixels
    found, ok = triangulate(camera, first, second, *seen, max_error=2.0, min_angle_deg=2.0)
    assert ok.tolist() == [True, False, False] and np.allclose(found[0], xyz[0], atol=1e-6)
