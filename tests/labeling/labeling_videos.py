"""A small synthetic video of a known moving textured blob (labeling tests)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

WIDTH, HEIGHT, FRAMES = 320, 240, 24
BLOB_RADIUS = 14


def blob_center(frame: int) -> tuple[float, float]:
    """Ground truth: the blob's centre in OpenCV pixels, a slow arc across the image."""
    t = frame / (FRAMES - 1)
    return 80.0 + 160.0 * t, 120.0 + 40.0 * np.sin(np.pi * t)


def render_frame(frame: int, background: np.ndarray, texture: np.ndarray) -> np.ndarray:
    image = background.copy()
    cx, cy = blob_center(frame)
    x0, y0 = round(cx) - BLOB_RADIUS, round(cy) - BLOB_RADIUS
    size = 2 * BLOB_RADIUS + 1
    yy, xx = np.mgrid[:size, :size]
    inside = (xx - BLOB_RADIUS) ** 2 + (yy - BLOB_RADIUS) ** 2 <= BLOB_RADIUS**2
    region = image[y0 : y0 + size, x0 : x0 + size]
    region[inside] = texture[inside]
    return image


def write_video(path: Path, frames: int = FRAMES, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, size=(HEIGHT // 4, WIDTH // 4, 3), dtype=np.uint8)
    background = cv2.resize(noise, (WIDTH, HEIGHT), interpolation=cv2.INTER_CUBIC)
    background = (0.5 * background + 40).astype(np.uint8)  # darker, so the blob stands out
    size = 2 * BLOB_RADIUS + 1
    checker = ((np.indices((size, size)) // 4).sum(axis=0) % 2).astype(np.uint8)
    texture = np.stack([checker * 200 + 40, checker * 120 + 100, 255 - checker * 200], axis=-1)
    texture = texture.astype(np.uint8)
    fourcc = cv2.VideoWriter.fourcc(*"MJPG")
    writer = cv2.VideoWriter(str(path), fourcc, 10.0, (WIDTH, HEIGHT))
    assert writer.isOpened(), "MJPG writer must be available in opencv-headless"
    for i in range(frames):
        writer.write(render_frame(i, background, texture))
    writer.release()
    return path
