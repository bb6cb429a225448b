"""Videos of a synthetic scene: camera paths at their own frame rates, moving spheres, ground-truth
cameras."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sfm.cameras import FrameCamera, VideoCameras
from sfm.synthetic.room import Room, Spheres, render


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """cam_from_world rotation (3, 3) of an upright OpenCV camera at `center` looking at `target` (z up
    world)."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    forward = np.asarray(target, dtype=float) - np.asarray(center, dtype=float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


@dataclass(kw_only=True)
class CameraPath:
    """A camera moving from `start` to `end` while looking from `target_start` to `target_end` (smooth in
    time)."""

    name: str
    K: np.ndarray  # (3, 3)
    width: int
    height: int
    fps: float
    num_frames: int
    start: np.ndarray  # (3,) centre at time 0
    end: np.ndarray  # (3,) centre at the last frame
    target_start: np.ndarray
    target_end: np.ndarray

    def times(self) -> np.ndarray:
        return np.arange(self.num_frames) / self.fps

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) cam_from_world at `time` seconds."""
        duration = max((self.num_frames - 1) / self.fps, 1e-9)
        s = _smoothstep(time / duration)
        center = (1 - s) * np.asarray(self.start) + s * np.asarray(self.end)
        target = (1 - s) * np.asarray(self.target_start) + s * np.asarray(self.target_end)
        R = look_at(center, target)
        return R, -R @ center


@dataclass(kw_only=True)
class SceneVideo:
    """One rendered video. `object_ids`: (F, H, W) int16, -1 room, i sphere i (ground-truth masks)."""

    path: Path
    cameras: VideoCameras
    object_ids: np.ndarray


def render_video(
    room: Room,
    camera: CameraPath,
    out_path: str | Path,
    spheres_at: Callable[[float], Spheres] | None = None,
    fourcc: str = "mp4v",
) -> SceneVideo:
    """Render every frame of `camera` into a video file; spheres come from `spheres_at(time)` (world time,
    s)."""
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out_path), cv2.VideoWriter.fourcc(*fourcc), camera.fps, (camera.width, camera.height))
    if not writer.isOpened():
        raise RuntimeError(f"cannot write {out_path} with fourcc {fourcc}")
    frames, ids = [], []
    try:
        for index, time in enumerate(camera.times()):
            R, t = camera.pose(float(time))
            spheres = spheres_at(float(time)) if spheres_at is not None else None
            image, _, object_id = render(room, camera.K, R, t, camera.width, camera.height, spheres)
            writer.write(image)
            ids.append(object_id.astype(np.int16))
            frames.append(FrameCamera(frame=index, time=float(time), K=camera.K.copy(), R=R, t=t))
    finally:
        writer.release()
    video = VideoCameras(name=camera.name, width=camera.width, height=camera.height, fps=camera.fps, frames=frames)
    return SceneVideo(path=out_path, cameras=video, object_ids=np.stack(ids))
