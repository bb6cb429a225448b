"""Generate `video_sample/`: three short unsynchronized videos of a walking figure in a textured room.

Made by project code only: the procedural walker of `make_walker.py` (joints in mm), walking on a treadmill, is
placed in the ray-cast room of `sfm.synthetic` (metres) as 18 checkered marker balls, filmed by three handheld-like
cameras at 30, 24 and 20 fps that start at different times. Written next to this script (run from the repo root):

    python data_samples/make_video_sample.py

Outputs (see docs/formats.md, "video sample"): `cam0.mp4 cam1.mp4 cam2.mp4` (VP9 in MP4: rerun plays it, OpenCV
decodes it), `labels.csv` (true projections of the visible joints on every 5th frame, 0.5 px noise: the clicks of
a user), `truth.csv` (true 3D joints at every frame's capture time, mm, renderer's world frame),
`truth_cameras.json` (true cameras, mm), `walker_skeleton.json` (points and bones) and `sample.json` (the
parameters). `cut_sample` makes a shorter copy for tests.
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
from reconstruct.outputs.points import FramePoints, write_points
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras
from sfm.synthetic.room import Room, Spheres
from sfm.synthetic.scene import CameraPath, SceneVideo, look_at, render_video

log = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
OUT = HERE / "video_sample"
WALKER_RATE = 120.0  # every capture time below is a multiple of 1/120 s, so the walker is sampled exactly
WIDTH, HEIGHT = 480, 360
JOINT_RADIUS_M = 0.045
LABEL_EVERY = 5  # frames; the fast joints (wrists, ankles, toes) lose their tracks within ~5 frames at 20 fps
LABEL_NOISE_PX = 0.5
SEED = 0
# The walker walks on a treadmill (its forward speed taken out) 2.2 m in front of the cameras, facing them, seen from
# the front-left, the front and the front-right. Why (measured with benchmarks/demo_diagnosis.py): walking towards
# the cameras took it from 5.2 m to 2.9 m away (12 mm per pixel at the start, markers a few pixels wide); walking
# across the view gave the front camera a side view where left and right markers hide each other. On the treadmill
# the distance stays ~2.2 m and every camera sees both sides of the body.
WALKER_OFFSET_M = np.array([4.0, 3.8, 0.03])
WALKER_TO_ROOM = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # forward -> -y, left -> +x
FOCAL_PER_WIDTH = 0.75  # focal / image width (times focal_scale): ~67 degrees across, the walker ~290 px tall
AIM_HEIGHT_M = 0.95  # the cameras aim at the walker at this height
MARKER_SQUARES = 8  # checker squares around each marker: black and white corners that LK tracks against the busy room


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


# Start times differ (as unsynchronized phones do) but by little, and all three videos end together, so nearly every
# instant is seen by every video (an instant seen by one video only has no triangulation to lean on).
SHOTS = (
    Shot(
        name="cam0",
        fps=30.0,
        start_s=0.0,
        num_frames=57,
        focal_scale=1.0,
        start=(2.45, 2.25, 1.5),
        move=(0.3, -0.3, 0.05),
    ),
    Shot(
        name="cam1",
        fps=24.0,
        start_s=0.05,
        num_frames=44,
        focal_scale=1.1,
        start=(3.8, 1.6, 1.6),
        move=(0.35, -0.3, 0.0),
    ),
    Shot(
        name="cam2",
        fps=20.0,
        start_s=0.1,
        num_frames=36,
        focal_scale=0.95,
        start=(5.4, 2.1, 1.3),
        move=(-0.3, -0.25, 0.1),
    ),
)


@dataclass(kw_only=True)
class HandheldPath(CameraPath):
    """A camera path with the slow sway of a hand: a few centimetres and under a degree, smooth in time."""

    phase: float = 0.0

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        duration = max((self.num_frames - 1) / self.fps, 1e-9)
        s = time / duration
        sway = np.array(
            [np.sin(2.1 * time + self.phase), np.sin(1.3 * time + 2 * self.phase), np.sin(1.7 * time + 3 * self.phase)]
        )
        center = (1 - s) * np.asarray(self.start) + s * np.asarray(self.end) + 0.02 * sway
        aim = np.array([np.sin(0.9 * time + self.phase), 0.0, np.cos(1.1 * time + self.phase)])
        target = (1 - s) * np.asarray(self.target_start) + s * np.asarray(self.target_end) + 0.04 * aim
        R = look_at(center, target)
        return R, -R @ center


def walker_metres(duration_s: float) -> np.ndarray:
    """(T, 18, 3) joint positions in the room (metres) at k / 120 s, walking on a treadmill in the middle of the
    room: the pelvis' mean forward speed is taken out of every joint (its sway stays; the feet slide back while on
    the ground, as on a treadmill)."""
    joints_mm = walker(rate=WALKER_RATE, duration=duration_s)
    t = np.arange(len(joints_mm)) / WALKER_RATE
    forward = np.polyval(np.polyfit(t, joints_mm[:, 0, 0], 1), t)  # (T,) the pelvis' straight-line progress
    joints_mm = joints_mm - forward[:, None, None] * np.array([1.0, 0.0, 0.0])
    return joints_mm @ WALKER_TO_ROOM.T / 1000.0 + WALKER_OFFSET_M


def subject_at(joints_m: np.ndarray) -> Callable[[float], Spheres]:
    """Spheres at the walker's joints at a true time (seconds, exact multiple of 1/120 s)."""

    texture = marker_texture()

    def spheres(true_time: float) -> Spheres:
        sample = round(true_time * WALKER_RATE)
        return Spheres(centers=joints_m[sample], radii=JOINT_RADIUS_M, texture=texture)

    return spheres


def marker_texture() -> np.ndarray:
    """(128, 256, 3) uint8 equirectangular black-and-white checker for the joint markers (like taped mocap balls):
    their corners stand out from the room's colour noise, so labels track frame to frame."""
    rows, cols = np.mgrid[0:128, 0:256]
    square = 256 // MARKER_SQUARES
    white = ((rows // square + cols // square) % 2).astype(bool)
    texture = np.full((128, 256, 3), 25, np.uint8)
    texture[white] = 235
    return texture


def camera_path(shot: Shot, index: int) -> HandheldPath:
    """The shot's handheld path, aimed at the walker (its sway moves the aim a little)."""
    f = FOCAL_PER_WIDTH * WIDTH * shot.focal_scale
    K = np.array([[f, 0.0, (WIDTH - 1) / 2], [0.0, f, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])
    start = np.array(shot.start)
    aim = np.array([*WALKER_OFFSET_M[:2], AIM_HEIGHT_M])
    return HandheldPath(
        name=shot.name,
        K=K,
        width=WIDTH,
        height=HEIGHT,
        fps=shot.fps,
        num_frames=shot.num_frames,
        start=start,
        end=start + np.array(shot.move),
        target_start=aim,
        target_end=aim,
        phase=1.7 * index,
    )


def _visible_projections(
    video: SceneVideo, joints_m: np.ndarray, start_s: float, fps: float, frame: int
) -> dict[int, np.ndarray]:
    """Joint index -> true pixel (2,) for joints whose own sphere is what the pixel shows (not occluded)."""
    camera = video.cameras.frames[frame]
    sample = round((start_s + frame / fps) * WALKER_RATE)
    x_cam = joints_m[sample] @ camera.R.T + camera.t
    uv = x_cam @ camera.K.T
    uv = uv[:, :2] / uv[:, 2:]
    visible = {}
    for joint, (u, v) in enumerate(uv):
        col, row = round(u), round(v)
        if (
            x_cam[joint, 2] > 0
            and 0 <= col < WIDTH
            and 0 <= row < HEIGHT
            and video.object_ids[frame, row, col] == joint
        ):
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
        video = render_video(
            room, path, out / f"{shot.name}.mp4", lambda t, s=shot, sp=spheres: sp(s.start_s + t), fourcc="vp09"
        )
        log.info(
            "%s: %d frames at %.0f fps in %.1f s (%.0f kB)",
            shot.name,
            shot.num_frames,
            shot.fps,
            time.perf_counter() - started,
            video.path.stat().st_size / 1000,
        )
        for frame in range(0, shot.num_frames, LABEL_EVERY):
            for joint, uv in _visible_projections(video, joints_m, shot.start_s, shot.fps, frame).items():
                x, y = uv + rng.normal(0.0, LABEL_NOISE_PX, 2)
                label_rows.append([shot.name, str(frame), JOINTS[joint], f"{x:.3f}", f"{y:.3f}", "label"])
        frames_mm = [
            FrameCamera(frame=c.frame, time=c.time, K=c.K, R=c.R, t=c.t * 1000.0) for c in video.cameras.frames
        ]
        truth_cameras.videos.append(
            VideoCameras(name=shot.name, width=WIDTH, height=HEIGHT, fps=shot.fps, frames=frames_mm)
        )
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
    write_points(
        out / "truth.csv",
        FramePoints(
            videos=truth_videos,
            frames=np.array(truth_frames),
            point_names=list(JOINTS),
            xyz=np.array(truth_xyz),
            observed=np.ones((count, len(JOINTS)), bool),
            extra={"time": np.repeat(np.array(truth_time)[:, None], len(JOINTS), axis=1)},
        ),
    )
    write_cameras(out / "truth_cameras.json", truth_cameras)
    (out / "walker_skeleton.json").write_text(json.dumps({"points": JOINTS, "connections": BONES}, indent=1) + "\n")
    (out / "sample.json").write_text(
        json.dumps(
            {
                "units": "mm (truth.csv, truth_cameras.json); the renderer works in metres",
                "size_px": [WIDTH, HEIGHT],
                "joint_radius_mm": JOINT_RADIUS_M * 1000,
                "label_every": LABEL_EVERY,
                "label_noise_px": LABEL_NOISE_PX,
                "seed": SEED,
                "videos": [{"name": s.name, "fps": s.fps, "start_s": s.start_s, "frames": s.num_frames} for s in SHOTS],
            },
            indent=1,
        )
        + "\n"
    )
    log.info("wrote %s: %d labels, %d truth frames", out, len(label_rows), count)


def cut_sample(out: Path, seconds: float, source: Path = OUT) -> Path:
    """A shorter copy of the sample in `out`: each video's frames of its first `seconds` (same frame rates, VP9
    again), with their labels, truth rows and true cameras (same frame numbers). For tests that run the whole
    pipeline in a fraction of the demo's time. Returns `out`."""
    import cv2

    from reconstruct.outputs.points import read_points
    from sfm.cameras import read_cameras

    out.mkdir(parents=True, exist_ok=True)
    meta = json.loads((source / "sample.json").read_text(encoding="utf-8"))
    keep = {v["name"]: max(2, min(v["frames"], int(np.ceil(seconds * v["fps"])))) for v in meta["videos"]}
    for name, count in keep.items():
        capture = cv2.VideoCapture(str(source / f"{name}.mp4"))
        fps = capture.get(cv2.CAP_PROP_FPS)
        frames = [capture.read()[1] for _ in range(count)]
        capture.release()
        writer = cv2.VideoWriter(str(out / f"{name}.mp4"), cv2.VideoWriter.fourcc(*"vp09"), fps, frames[0].shape[1::-1])
        for image in frames:
            writer.write(image)
        writer.release()
    with (source / "labels.csv").open(newline="") as handle:
        rows = list(csv.reader(handle))
    with (out / "labels.csv").open("w", newline="") as handle:
        csv.writer(handle, lineterminator="\n").writerows([rows[0], *(r for r in rows[1:] if int(r[1]) < keep[r[0]])])
    truth = read_points(source / "truth.csv")
    rows_kept = [i for i, (v, f) in enumerate(zip(truth.videos, truth.frames, strict=True)) if f < keep[v]]
    write_points(
        out / "truth.csv",
        FramePoints(
            videos=[truth.videos[i] for i in rows_kept],
            frames=truth.frames[rows_kept],
            point_names=truth.point_names,
            xyz=truth.xyz[rows_kept],
            observed=truth.observed[rows_kept],
            extra={k: v[rows_kept] for k, v in truth.extra.items()},
        ),
    )
    cameras = read_cameras(source / "truth_cameras.json")
    for video in cameras.videos:
        video.frames = [f for f in video.frames if f.frame < keep[video.name]]
    write_cameras(out / "truth_cameras.json", cameras)
    (out / "walker_skeleton.json").write_text((source / "walker_skeleton.json").read_text(encoding="utf-8"))
    for video in meta["videos"]:
        video["frames"] = keep[video["name"]]
    meta["cut_from"] = {"seconds": seconds}
    (out / "sample.json").write_text(json.dumps(meta, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
