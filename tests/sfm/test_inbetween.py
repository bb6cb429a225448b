"""In-between frames posed by tracking the keyframes' features (`sfm.track_pose`), SIFT where tracking fails.

One small synthetic handheld capture (2 videos x 14 frames, 4 SfM frames each) is registered once; in cam0 one frame
is rendered with the camera turned away by a sudden pan, which optical flow cannot follow: that frame must come from
the SIFT path, every other in-between frame from tracking, and the report must say so per frame.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras
from sfm.evaluate import compare
from sfm.synthetic.demo import three_cameras
from sfm.synthetic.room import Room, render
from sfm.synthetic.scene import CameraPath
from sfm.track_pose import segments, spread

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
        paths = {p["frame"]: p["path"] for p in video["posed"]}
        assert len(paths) == FRAMES and video["failed"] == []
        assert [f for f, p in paths.items() if p == "sfm"] == [0, 4, 9, 13]
        lost = [JUMP] if name == "cam0" else []
        assert [f for f, p in paths.items() if p == "sift"] == lost
        assert video["registered_by_tracking"] == FRAMES - 4 - len(lost)
        assert all(p["inliers"] >= 30 for p in video["posed"])


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
