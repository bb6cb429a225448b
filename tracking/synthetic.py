"""Tracking ground truth: a rendered video of textured markers moving over a textured background.

The camera pans, rotates and zooms (a 2D similarity of the background per frame), each marker follows its own
smooth path and spins, every frame is the mean of several sub-frame renders inside the shutter time (motion
blur), a textured bar sweeps across the picture and hides the markers it covers (occlusion), and sensor noise
is added. The ground truth is each marker centre at the middle of the exposure (`uv: (F, P, 2)`, OpenCV pixel
convention) and whether it is visible (`visible: (F, P)`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

ZOOM = 0.05  # amplitude of the camera's relative scale change over the video
OCCLUDER_WIDTH = 0.08  # width of the occluding bar, as a fraction of the image width
FPS = 30.0  # frame rate written into the video file


@dataclass(kw_only=True)
class SyntheticOptions:
    width: int = 640
    height: int = 480
    frames: int = 60
    markers: int = 8
    marker_radius: float = 12.0  # pixels at scale 1
    speed: float = 3.0  # typical marker speed, pixels per frame
    pan: float = 1.5  # typical camera pan, pixels per frame
    rotation_deg: float = 3.0  # amplitude of the camera roll over the video
    blur_samples: int = 5  # sub-frame renders averaged per frame (1: no motion blur)
    exposure: float = 0.6  # shutter open time as a fraction of the frame interval
    occluder: bool = True  # a bar sweeps across the picture during the middle half of the video
    noise: float = 1.5  # sensor noise, standard deviation in gray levels
    flicker: float = 0.0  # auto-exposure flicker: standard deviation of a per-frame relative gain change
    fourcc: str = "FFV1"  # FFV1 in .avi is lossless; "mp4v" in .mp4 adds compression artefacts
    seed: int = 0


@dataclass(kw_only=True)
class SyntheticVideo:
    path: Path | None
    names: list[str]  # (P,)
    uv: np.ndarray  # (F, P, 2) marker centres, pixels
    visible: np.ndarray  # (F, P) bool: centre inside the image and not under the occluder
    frames: list[np.ndarray] | None = None  # (H, W, 3) BGR uint8 each, when kept in memory


def _texture(rng: np.random.Generator, height: int, width: int, scales: tuple[float, ...]) -> np.ndarray:
    """(H, W, 3) float32 BGR in 0..255: coloured noise at several scales, so LK has gradients at every
    level."""
    out = np.zeros((height, width, 3), np.float32)
    for sigma in scales:
        noise = rng.standard_normal((height, width, 3)).astype(np.float32)
        layer = np.asarray(cv2.GaussianBlur(noise, (0, 0), sigma), dtype=np.float32)
        layer /= layer.std() + 1e-6
        out += layer
    out = (out - out.mean()) / (out.std() + 1e-6)
    return np.clip(128 + 45 * out, 0, 255).astype(np.float32)


class _Scene:
    def __init__(self, options: SyntheticOptions):
        self.o = options
        rng = np.random.default_rng(options.seed)
        w, h = options.width, options.height
        # The background is larger than the picture so that panning, rolling and zooming never show its edge.
        self.pad = int(0.35 * max(w, h) + options.pan * options.frames)
        self.background = _texture(rng, h + 2 * self.pad, w + 2 * self.pad, (1.0, 3.0, 9.0))
        r = math.ceil(options.marker_radius)
        size = 2 * r + 1
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) - r
        dist = np.hypot(xx, yy)
        self.marker_half = r
        self.alpha = np.clip(options.marker_radius + 0.5 - dist, 0, 1).astype(np.float32)
        self.marker_textures = []
        for _ in range(options.markers):
            tex = _texture(rng, size, size, (1.0, 2.0))
            # A dark ring and a bright core: high contrast against any background, like a painted marker.
            ring = (dist > 0.75 * options.marker_radius).astype(np.float32)
            tex = tex * (1 - 0.6 * ring)[:, :, None]
            self.marker_textures.append(tex)
        # Paths in picture coordinates of frame 0 (the camera moves on top): a centre plus two sinusoids.
        margin = 0.15
        self.centres = np.column_stack(
            [
                rng.uniform(margin * w, (1 - margin) * w, options.markers),
                rng.uniform(margin * h, (1 - margin) * h, options.markers),
            ]
        )
        self.freq = rng.uniform(0.5, 2.0, (options.markers, 2, 2)) * 2 * math.pi / max(options.frames, 1)
        self.phase = rng.uniform(0, 2 * math.pi, (options.markers, 2, 2))
        amplitude = options.speed / self.freq / 2  # two sinusoids per axis: speed about options.speed
        self.amp = np.minimum(amplitude, (0.45 * margin * np.array([w, h]))[None, :, None])
        self.spin = rng.uniform(-0.05, 0.05, options.markers)  # radians per frame
        self.cam_phase = rng.uniform(0, 2 * math.pi, 4)
        self.occluder_tex = _texture(rng, h, max(4, int(OCCLUDER_WIDTH * w)) + 8, (1.0, 4.0))

    def marker_xy(self, t: float) -> np.ndarray:
        """(P, 2) marker centres in frame-0 picture coordinates."""
        wave = self.amp * np.sin(self.freq * t + self.phase)  # (P, 2, 2)
        return self.centres + wave.sum(axis=2)

    def camera(self, t: float) -> np.ndarray:
        """(2, 3) affine from frame-0 picture coordinates to the picture at time t (a similarity)."""
        o = self.o
        n = max(o.frames, 1)
        angle = math.radians(o.rotation_deg) * math.sin(2 * math.pi * t / n + self.cam_phase[0])
        scale = 1.0 + ZOOM * math.sin(2 * math.pi * t / n + self.cam_phase[1])
        tx = o.pan * t + 0.3 * o.pan * n / (2 * math.pi) * math.sin(2 * math.pi * t / n + self.cam_phase[2])
        ty = 0.5 * o.pan * n / (2 * math.pi) * math.sin(2 * math.pi * t / n + self.cam_phase[3])
        cx, cy = o.width / 2, o.height / 2
        c, s = scale * math.cos(angle), scale * math.sin(angle)
        # Rotate and scale about the picture centre, then pan (the scene moves opposite to the camera).
        return np.array([[c, -s, cx - c * cx + s * cy - tx], [s, c, cy - s * cx - c * cy - ty]])

    def occluder_x(self, t: float) -> float | None:
        """Left edge of the occluding bar at time t (it crosses during the middle half), None when absent."""
        if not self.o.occluder:
            return None
        n = max(self.o.frames, 1)
        start, end = n / 4, 3 * n / 4
        bar = self.occluder_tex.shape[1]
        return -bar + (t - start) / (end - start) * (self.o.width + bar)

    def render(self, t: float) -> np.ndarray:
        """(H, W, 3) float32 picture at exact time t (no blur, no noise)."""
        o = self.o
        A = self.camera(t)
        # The background texture's pixel (pad, pad) is frame-0 picture pixel (0, 0).
        to_bg = A @ np.array([[1, 0, -self.pad], [0, 1, -self.pad], [0, 0, 1]], float)
        picture = cv2.warpAffine(
            self.background, to_bg, (o.width, o.height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        xy = self.marker_xy(t)
        r = self.marker_half
        for p in range(o.markers):
            theta = self.spin[p] * t
            c, s = math.cos(theta), math.sin(theta)
            local = np.array([[c, -s, xy[p, 0] - c * r + s * r], [s, c, xy[p, 1] - s * r - c * r], [0, 0, 1]])
            # marker texture pixel -> picture pixel; the texture centre (r, r) lands on the marker centre
            M = A @ local
            centre = A @ np.array([xy[p, 0], xy[p, 1], 1.0])
            half = math.ceil(1.5 * r) + 2
            x0, y0 = math.floor(centre[0]) - half, math.floor(centre[1]) - half
            x1, y1 = x0 + 2 * half + 1, y0 + 2 * half + 1
            cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, o.width), min(y1, o.height)
            if cx0 >= cx1 or cy0 >= cy1:
                continue
            roi = M.copy()
            roi[:, 2] -= (cx0, cy0)
            size = (cx1 - cx0, cy1 - cy0)
            tex = cv2.warpAffine(
                self.marker_textures[p], roi, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
            )
            alpha = cv2.warpAffine(self.alpha, roi, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            window = picture[cy0:cy1, cx0:cx1]
            window[:] = window * (1 - alpha[:, :, None]) + tex * alpha[:, :, None]
        left = self.occluder_x(t)
        if left is not None:
            bar = self.occluder_tex.shape[1]
            shift = np.array([[1, 0, left], [0, 1, 0]], float)
            tex = cv2.warpAffine(
                self.occluder_tex,
                shift,
                (o.width, o.height),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=(-1, -1, -1),
            )
            if -bar < left < o.width:
                ones = np.ones((o.height, bar), np.float32)
                mask = cv2.warpAffine(
                    ones, shift, (o.width, o.height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
                )
                picture = picture * (1 - mask[:, :, None]) + np.maximum(tex, 0) * mask[:, :, None]
        return picture

    def truth(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(P, 2) picture positions and (P,) visibility at time t."""
        o = self.o
        xy = self.marker_xy(t)
        uv = (self.camera(t) @ np.column_stack([xy, np.ones(len(xy))]).T).T
        visible = (uv[:, 0] >= 0) & (uv[:, 0] <= o.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= o.height - 1)
        left = self.occluder_x(t)
        if left is not None:
            bar = self.occluder_tex.shape[1]
            visible &= ~((uv[:, 0] >= left - 0.5) & (uv[:, 0] <= left + bar - 0.5))
        return uv, visible


def render_video(
    path: str | Path | None,
    options: SyntheticOptions | None = None,
    *,
    keep_frames: bool = False,
    progress: Callable[[int], None] | None = None,
) -> SyntheticVideo:
    """Render the video to `path` with `cv2.VideoWriter` (None: only in memory, then `keep_frames` is
    implied)."""
    options = options or SyntheticOptions()
    scene = _Scene(options)
    rng = np.random.default_rng(options.seed + 1)
    writer = None
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter.fourcc(*options.fourcc), FPS, (options.width, options.height)
        )
        if not writer.isOpened():
            raise RuntimeError(f"cv2.VideoWriter cannot write {options.fourcc!r} to {path}")
    keep = keep_frames or path is None
    frames: list[np.ndarray] = []
    uv = np.zeros((options.frames, options.markers, 2))
    visible = np.zeros((options.frames, options.markers), bool)
    samples = max(1, options.blur_samples)
    offsets = [0.0] if samples == 1 else list(options.exposure * (np.arange(samples) / (samples - 1) - 0.5))
    for f in range(options.frames):
        picture = np.mean([scene.render(f + dt) for dt in offsets], axis=0)
        if options.flicker > 0:
            picture *= float(np.clip(1.0 + options.flicker * rng.standard_normal(), 0.3, 2.0))
        picture += rng.normal(0, options.noise, picture.shape).astype(np.float32)
        image = np.clip(np.rint(picture), 0, 255).astype(np.uint8)
        uv[f], visible[f] = scene.truth(f)
        if writer is not None:
            writer.write(image)
        if keep:
            frames.append(image)
        if progress is not None:
            progress(f)
    if writer is not None:
        writer.release()
    return SyntheticVideo(
        path=Path(path) if path is not None else None,
        names=[f"m{p}" for p in range(options.markers)],
        uv=uv,
        visible=visible,
        frames=frames if keep else None,
    )
