"""A ready-made test scene: three cameras at different frame rates and focal lengths moving inside the room
while
four textured spheres orbit and spin in its middle."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sfm.synthetic.room import Room, Spheres
from sfm.synthetic.scene import CameraPath, SceneVideo, render_video
from tracking.tracks import Tracks


def orbiting_spheres(time: float, count: int = 4) -> Spheres:
    """`count` spheres circling the room's middle, each spinning about z (known 3D motion)."""
    phase = 1.5 * time + np.arange(count) * 2 * np.pi / count
    centers = np.stack([4.0 + 0.9 * np.cos(phase), 3.2 + 0.9 * np.sin(phase), 0.9 + 0.25 * np.arange(count)], 1)
    spin = 2.0 * time
    rotation = np.array([[np.cos(spin), np.sin(spin), 0.0], [-np.sin(spin), np.cos(spin), 0.0], [0.0, 0.0, 1.0]])
    return Spheres(centers=centers, radii=0.3, rotations=np.repeat(rotation[None], count, axis=0))


def three_cameras(
    width: int = 640,
    height: int = 480,
    frames: tuple[int, int, int] = (20, 16, 12),
    fps: tuple[float, float, float] = (30.0, 24.0, 18.0),
) -> list[CameraPath]:
    """Three cameras on the room's y=0 side, 3-4 m apart, each moving ~1.3 m while panning across the far
    wall."""
    paths = []
    setups = [
        (1.00, [1.2, 0.8, 1.5], [1.0, 0.8, 0.3], [6.0, 5.0, 1.3]),
        (1.12, [4.0, 0.6, 1.7], [-1.0, 0.5, 0.3], [4.2, 5.5, 1.2]),
        (0.92, [6.8, 0.9, 1.3], [-0.6, 1.0, 0.4], [2.0, 5.0, 1.4]),
    ]
    for index, ((focal, start, move, target), count, rate) in enumerate(zip(setups, frames, fps, strict=True)):
        f = 0.78 * width * focal
        K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
        start_c = np.array(start)
        paths.append(
            CameraPath(
                name=f"cam{index}",
                K=K,
                width=width,
                height=height,
                fps=rate,
                num_frames=count,
                start=start_c,
                end=start_c + move,
                target_start=np.array(target),
                target_end=np.array(target) + np.array([0.6, 0.0, -0.2]),
            )
        )
    return paths


def mixed_cameras(width: int = 480, height: int = 360, frames: int = 12) -> list[CameraPath]:
    """A mixed static + handheld capture: two tripods high in the near corners (30 and 25 fps) looking across the
    room at ~90 degrees from each other, and a handheld camera (24 fps) walking between them."""
    setups = [  # (name, focal / width, fps, start, end, target at start, target at end)
        ("cam0", 0.7, 30.0, [0.5, 0.5, 2.3], [0.5, 0.5, 2.3], [5.0, 4.5, 0.6], [5.0, 4.5, 0.6]),
        ("cam1", 0.8, 24.0, [2.6, 0.3, 1.6], [4.8, 0.4, 1.7], [3.0, 5.5, 1.0], [5.5, 5.0, 1.2]),
        ("cam2", 0.75, 25.0, [7.5, 0.6, 2.2], [7.5, 0.6, 2.2], [2.5, 4.5, 0.7], [2.5, 4.5, 0.7]),
    ]
    paths = []
    for name, focal, rate, start, end, target_start, target_end in setups:
        f = focal * width
        K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
        paths.append(
            CameraPath(
                name=name,
                K=K,
                width=width,
                height=height,
                fps=rate,
                num_frames=frames,
                start=np.array(start),
                end=np.array(end),
                target_start=np.array(target_start),
                target_end=np.array(target_end),
            )
        )
    return paths


def render_demo(out_dir: str | Path, cameras: list[CameraPath] | None = None, seed: int = 0) -> list[SceneVideo]:
    """Render the demo scene's videos (mp4v) into out_dir; returns them with their ground-truth cameras."""
    room = Room(seed=seed)
    return [
        render_video(room, camera, Path(out_dir) / f"{camera.name}.mp4", orbiting_spheres)
        for camera in (cameras or three_cameras())
    ]


def sphere_tracks(videos: list[SceneVideo]) -> Tracks:
    """Ground-truth 2D tracks of the orbiting spheres' centres in each rendered frame (what the tracking stage
    would deliver), for masking the moving subject out of SfM."""
    rows = []
    for video in videos:
        for frame in video.cameras.frames:
            if frame.time is None:
                raise ValueError(f"rendered frame {frame.frame} of {video.cameras.name} has no capture time")
            centers = orbiting_spheres(frame.time).centers
            in_cam = centers @ frame.R.T + frame.t
            uv = in_cam @ frame.K.T
            for index, (point, depth) in enumerate(zip(uv, in_cam[:, 2], strict=True)):
                x, y = point[:2] / point[2]
                if depth > 0 and 0 <= x < video.cameras.width and 0 <= y < video.cameras.height:
                    rows.append((video.cameras.name, frame.frame, f"sphere{index}", float(x), float(y)))
    return Tracks.from_rows(rows)
