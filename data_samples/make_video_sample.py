"""Generate `video_sample/`: three short unsynchronized videos of a walking figure in a textured room.

Made by project code only: the procedural walker of `make_walker.py` (joints in mm) is scaled into the ray-cast
room of `sfm.synthetic` (metres) as textured spheres, filmed by three handheld-like cameras at 30, 24 and 20 fps
that start at different times. Written next to this script (run from the repo root):

    python data_samples/make_video_sample.py

Outputs (see docs/formats.md, "video sample"): `cam0.mp4 cam1.mp4 cam2.mp4` (VP9 in MP4: rerun plays it, OpenCV
decodes it), `labels.csv` (true joint projections on every 10th frame, 0.5 px noise: the clicks of a user),
`truth.csv` (true 3D joints at every frame's capture time, mm, renderer's world frame), `truth_cameras.json`
(true cameras, mm), `walker_skeleton.json` (points and bones) and `sample.json` (the parameters).
"""

from __future__ import annotations

import csv
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_samples.make_walker import BONES, JOINTS, walker
from reconstruct.points import FramePoints, write_points
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras
from sfm.synthetic.room import Room, Spheres
from sfm.synthetic.scene import CameraPath, SceneVideo, look_at, render_video

log = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
OUT = HERE / "video_sample"
WALKER_RATE = 120.0  # every capture time below is a multiple of 1/120 s, so the walker is sampled exactly
WIDTH, HEIGHT = 480, 360
JOINT_RADIUS_M = 0.05
LABEL_EVERY = 10
LABEL_NOISE_PX = 0.5
SEED = 0
# Walker placement in the room (metres): walking towards the cameras (-y) through the middle of the room, so that
# its left and right sides are both in view (walking across the view hides one side behind the other).
WALKER_OFFSET_M = np.array([4.0, 4.2, 0.03])
WALKER_TO_ROOM = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # forward -> -y, left -> +x


@dataclass(kw_only=True)
class Shot:
    """One handheld video: `fps`, start time on the true clock, frame count, and where it stands and looks."""

    name: str
    fps: float
    start_s: float  # multiple of 1/120 s
    num_frames: int
    focal_scale: float
    start: tuple[float, float, float]
    move: tuple[float, float, float]
    target: tuple[float, float, float]


SHOTS = (
    Shot(name="cam0", fps=30.0, start_s=0.0, num_frames=57, focal_scale=1.0,
         start=(1.8, 0.7, 1.5), move=(0.6, 0.1, 0.1), target=(4.1, 4.2, 0.9)),
    Shot(name="cam1", fps=24.0, start_s=0.15, num_frames=44, focal_scale=1.1,
         start=(4.3, 0.6, 1.7), move=(-0.5, 0.2, 0.0), target=(4.0, 4.2, 0.9)),
    Shot(name="cam2", fps=20.0, start_s=0.3, num_frames=36, focal_scale=0.95,
         start=(6.4, 0.8, 1.3), move=(-0.4, 0.2, 0.2), target=(3.9, 4.2, 1.0)),
)


@dataclass(kw_only=True)
class HandheldPath(CameraPath):
    """A camera path with the slow sway of a hand: a few centimetres and under a degree, smooth in time."""

    phase: float = 0.0

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        duration = max((self.num_frames - 1) / self.fps, 1e-9)
        s = time / duration
        sway = np.array([np.sin(2.1 * time + self.phase), np.sin(1.3 * time + 2 * self.phase),
                         np.sin(1.7 * time + 3 * self.phase)])
        center = (1 - s) * np.asarray(self.start) + s * np.asarray(self.end) + 0.02 * sway
        aim = np.array([np.sin(0.9 * time + self.phase), 0.0, np.cos(1.1 * time + self.phase)])
        target = (1 - s) * np.asarray(self.target_start) + s * np.asarray(self.target_end) + 0.04 * aim
        R = look_at(center, target)
        return R, -R @ center


def walker_metres(duration_s: float) -> np.ndarray:
    """(T, 18, 3) joint positions in the room (metres) at k / 120 s, walking through the middle of the room."""
    joints_mm = walker(rate=WALKER_RATE, duration=duration_s)
    centre_x = 0.5 * (joints_mm[0, 0, 0] + joints_mm[-1, 0, 0])
    shift = np.array([centre_x, 0.0, 0.0])
    return (joints_mm - shift) @ WALKER_TO_ROOM.T / 1000.0 + WALKER_OFFSET_M


def subject_at(joints_m: np.ndarray) -> Callable[[float], Spheres]:
    """Spheres at the walker's joints at a true time (seconds, exact multiple of 1/120 s)."""

    def spheres(true_time: float) -> Spheres:
        sample = round(true_time * WALKER_RATE)
        return Spheres(centers=joints_m[sample], radii=JOINT_RADIUS_M)

    return spheres


def camera_path(shot: Shot, index: int) -> HandheldPath:
    f = 0.85 * WIDTH * shot.focal_scale
    K = np.array([[f, 0.0, (WIDTH - 1) / 2], [0.0, f, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])
    start = np.array(shot.start)
    return HandheldPath(name=shot.name, K=K, width=WIDTH, height=HEIGHT, fps=shot.fps, num_frames=shot.num_frames,
                        start=start, end=start + np.array(shot.move), target_start=np.array(shot.target),
                        target_end=np.array(shot.target) + np.array([0.0, -0.8, 0.0]), phase=1.7 * index)


def _visible_projections(video: SceneVideo, joints_m: np.ndarray, start_s: float, fps: float,
                         frame: int) -> dict[int, np.ndarray]:
    """Joint index -> true pixel (2,) for joints whose own sphere is what the pixel shows (not occluded)."""
    camera = video.cameras.frames[frame]
    sample = round((start_s + frame / fps) * WALKER_RATE)
    x_cam = joints_m[sample] @ camera.R.T + camera.t
    uv = x_cam @ camera.K.T
    uv = uv[:, :2] / uv[:, 2:]
    visible = {}
    for joint, (u, v) in enumerate(uv):
        col, row = round(u), round(v)
        if x_cam[joint, 2] > 0 and 0 <= col < WIDTH and 0 <= row < HEIGHT and \
                video.object_ids[frame, row, col] == joint:
            visible[joint] = np.array([u, v])
    return visible


def main(out: Path = OUT) -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(SEED)
    end_s = max(shot.start_s + (shot.num_frames - 1) / shot.fps for shot in SHOTS)
    joints_m = walker_metres(end_s + 2 / WALKER_RATE)
    room = Room(seed=SEED)
    label_rows: list[list[str]] = []
    truth_cameras = CameraSet()
    truth_videos: list[str] = []
    truth_frames: list[int] = []
    truth_xyz: list[np.ndarray] = []
    truth_time: list[float] = []
    for index, shot in enumerate(SHOTS):
        started = time.perf_counter()
        path = camera_path(shot, index)
        spheres = subject_at(joints_m)
        video = render_video(room, path, out / f"{shot.name}.mp4",
                             lambda t, s=shot, sp=spheres: sp(s.start_s + t), fourcc="vp09")
        log.info("%s: %d frames at %.0f fps in %.1f s (%.0f kB)", shot.name, shot.num_frames, shot.fps,
                 time.perf_counter() - started, video.path.stat().st_size / 1000)
        for frame in range(0, shot.num_frames, LABEL_EVERY):
            for joint, uv in _visible_projections(video, joints_m, shot.start_s, shot.fps, frame).items():
                x, y = uv + rng.normal(0.0, LABEL_NOISE_PX, 2)
                label_rows.append([shot.name, str(frame), JOINTS[joint], f"{x:.3f}", f"{y:.3f}", "label"])
        frames_mm = [FrameCamera(frame=c.frame, time=c.time, K=c.K, R=c.R, t=c.t * 1000.0)
                     for c in video.cameras.frames]
        truth_cameras.videos.append(VideoCameras(name=shot.name, width=WIDTH, height=HEIGHT, fps=shot.fps,
                                                 frames=frames_mm))
        for frame in range(shot.num_frames):
            true_time = shot.start_s + frame / shot.fps
            truth_videos.append(shot.name)
            truth_frames.append(frame)
            truth_xyz.append(joints_m[round(true_time * WALKER_RATE)] * 1000.0)
            truth_time.append(true_time)
    with (out / "labels.csv").open("w", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(["video", "frame", "point", "x", "y", "source"])
        writer.writerows(label_rows)
    count = len(truth_videos)
    write_points(out / "truth.csv", FramePoints(
        videos=truth_videos, frames=np.array(truth_frames), point_names=list(JOINTS), xyz=np.array(truth_xyz),
        observed=np.ones((count, len(JOINTS)), bool),
        extra={"time": np.repeat(np.array(truth_time)[:, None], len(JOINTS), axis=1)}))
    write_cameras(out / "truth_cameras.json", truth_cameras)
    (out / "walker_skeleton.json").write_text(json.dumps({"points": JOINTS, "connections": BONES}, indent=1) + "\n")
    (out / "sample.json").write_text(json.dumps({
        "units": "mm (truth.csv, truth_cameras.json); the renderer works in metres",
        "size_px": [WIDTH, HEIGHT], "joint_radius_mm": JOINT_RADIUS_M * 1000, "label_every": LABEL_EVERY,
        "label_noise_px": LABEL_NOISE_PX, "seed": SEED,
        "videos": [{"name": s.name, "fps": s.fps, "start_s": s.start_s, "frames": s.num_frames} for s in SHOTS],
    }, indent=1) + "\n")
    log.info("wrote %s: %d labels, %d truth frames", out, len(label_rows), count)


if __name__ == "__main__":
    main()
