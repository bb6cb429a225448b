"""Ray casting of a textured box room with textured spheres inside, vectorized over pixels.

World frame: the room spans [0, size[0]] x [0, size[1]] x [0, size[2]] metres, z up. Cameras follow OpenCV (x
right,
y down, z forward), poses are cam_from_world, pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

TEXELS_PER_METRE = 160  # texture resolution on walls: ~2 texels per pixel at 3 m with f = 500


def noise_texture(shape: tuple[int, int], rng: np.random.Generator, *, shapes: int = 0) -> np.ndarray:
    """Colour texture rich in corners at several scales: blurred noise octaves plus random filled shapes.

    Returns (H, W, 3) uint8 BGR. Octaves are blurred to >= 1.5 texels so bilinear lookups do not alias much.
    """
    height, width = shape
    image = np.zeros((height, width, 3), np.float32)
    for sigma, weight in ((24.0, 1.0), (8.0, 0.8), (3.0, 0.6), (1.5, 0.4)):
        white = rng.normal(size=(height, width, 3)).astype(np.float32)
        octave = np.asarray(cv2.GaussianBlur(white, (0, 0), sigma), np.float32)
        image += (weight / (float(octave.std()) + 1e-6)) * octave
    canvas = np.clip(128 + 30 * image, 0, 255).astype(np.uint8)
    for _ in range(shapes):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        center = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        size = int(rng.integers(6, max(7, min(width, height) // 12)))
        if rng.random() < 0.5:
            cv2.circle(canvas, center, size, color, -1, cv2.LINE_AA)
        else:
            corner = (center[0] + size, center[1] + int(rng.integers(4, size + 5)))
            cv2.rectangle(canvas, center, corner, color, -1, cv2.LINE_AA)
    return canvas


@dataclass(kw_only=True)
class Room:
    """A box room with one texture per wall (order: x=0, x=max, y=0, y=max, z=0 floor, z=max ceiling)."""

    size: np.ndarray = field(default_factory=lambda: np.array([8.0, 6.0, 3.0]))  # (3,) metres
    seed: int = 0
    textures: list[np.ndarray] = field(default_factory=list)  # 6 x (H, W, 3) uint8

    def __post_init__(self) -> None:
        self.size = np.asarray(self.size, dtype=float)
        if not self.textures:
            rng = np.random.default_rng(self.seed)
            for axis in range(3):
                u_axis, v_axis = [a for a in range(3) if a != axis]
                shape = (int(self.size[v_axis] * TEXELS_PER_METRE), int(self.size[u_axis] * TEXELS_PER_METRE))
                for _ in range(2):
                    area = shape[0] * shape[1]
                    self.textures.append(noise_texture(shape, rng, shapes=area // 4000))


@dataclass(kw_only=True)
class Spheres:
    """Textured spheres at one instant. centers (P, 3), radii (P,); rotations (P, 3, 3) object_from_world
    spin."""

    centers: np.ndarray
    radii: np.ndarray | float
    rotations: np.ndarray | None = None
    texture: np.ndarray | None = None  # (H, W, 3) uint8 equirectangular map shared by all spheres
    texture_offsets: np.ndarray | None = None  # (P,) longitudes (texels) so that spheres look different

    def __post_init__(self) -> None:
        self.centers = np.asarray(self.centers, dtype=float).reshape(-1, 3)
        self.radii = np.broadcast_to(np.asarray(self.radii, dtype=float), (len(self.centers),)).copy()
        if self.texture is None:
            self.texture = noise_texture((256, 512), np.random.default_rng(1234), shapes=40)
        if self.texture_offsets is None:
            self.texture_offsets = (np.arange(len(self.centers)) * 97) % self.texture.shape[1]


def _rays(K: np.ndarray, R: np.ndarray, width: int, height: int) -> np.ndarray:
    """World-frame unit ray directions of every pixel centre, (H, W, 3)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    directions = pixels @ np.linalg.inv(K).T @ R  # (R^T d_cam)^T = d_cam^T R
    return directions / np.linalg.norm(directions, axis=-1, keepdims=True)


def _lookup(texture: np.ndarray, u: np.ndarray, v: np.ndarray, wrap: bool = False) -> np.ndarray:
    """Bilinear texture lookup at texel coordinates (any shape); returns (..., 3) float32."""
    shape = u.shape
    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REFLECT
    # remap wants maps under 32767 per side: lay the N lookups out as rows of 1024.
    count = u.size
    padded = -(-count // 1024) * 1024
    map_u = np.zeros(padded, np.float32)
    map_v = np.zeros(padded, np.float32)
    map_u[:count], map_v[:count] = u.ravel(), v.ravel()
    out = cv2.remap(
        texture, map_u.reshape(-1, 1024), map_v.reshape(-1, 1024), cv2.INTER_LINEAR, borderMode=border
    ).reshape(-1, 3)[:count]
    return out.reshape(*shape, 3).astype(np.float32)


def render(
    room: Room,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    width: int,
    height: int,
    spheres: Spheres | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view. Returns image (H, W, 3) uint8 BGR, depth (H, W) along the ray in metres, and object id
    (H, W) int32: -1 for the room, i for sphere i (a ground-truth mask of the moving objects)."""
    origin = -R.T @ t
    if np.any(origin <= 0) or np.any(origin >= room.size):
        raise ValueError(f"camera centre {origin} is outside the room {room.size}")
    d = _rays(K, R, width, height)
    with np.errstate(divide="ignore", invalid="ignore"):
        bounds = np.where(d > 0, room.size, 0.0)
        exit_t = np.where(d != 0, (bounds - origin) / d, np.inf)  # (H, W, 3)
    axis = np.argmin(exit_t, axis=-1)
    depth = np.take_along_axis(exit_t, axis[..., None], axis=-1)[..., 0]
    hit = origin + d * depth[..., None]
    wall = axis * 2 + (np.take_along_axis(d, axis[..., None], axis=-1)[..., 0] > 0)
    image = np.zeros((height, width, 3), np.float32)
    for index, texture in enumerate(room.textures):
        mask = wall == index
        if not mask.any():
            continue
        a = index // 2
        u_axis, v_axis = [x for x in range(3) if x != a]
        texel_u = hit[mask][:, u_axis] * TEXELS_PER_METRE - 0.5
        texel_v = hit[mask][:, v_axis] * TEXELS_PER_METRE - 0.5
        image[mask] = _lookup(texture, texel_u, texel_v)
    object_id = np.full((height, width), -1, np.int32)
    if spheres is not None and len(spheres.centers):
        assert spheres.texture is not None and spheres.texture_offsets is not None
        for i, (center, radius) in enumerate(zip(spheres.centers, np.asarray(spheres.radii), strict=True)):
            oc = origin - center
            b = d @ oc
            disc = b * b - (oc @ oc - radius * radius)
            inside = disc > 0
            if not inside.any():
                continue
            t_hit = np.where(inside, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
            front = inside & (t_hit > 0) & (t_hit < depth)
            if not front.any():
                continue
            depth = np.where(front, t_hit, depth)
            object_id[front] = i
            normal_world = (origin + d[front] * t_hit[front][:, None] - center) / radius
            # Lambert-like shading towards the viewer so spheres read as 3D; texture drives the features.
            shade = 0.55 + 0.45 * np.clip(-(d[front] * normal_world).sum(axis=1), 0, 1)
            normal = normal_world if spheres.rotations is None else normal_world @ spheres.rotations[i].T
            lon = np.arctan2(normal[:, 1], normal[:, 0])
            lat = np.arcsin(np.clip(normal[:, 2], -1, 1))
            tex_h, tex_w = spheres.texture.shape[:2]
            texel_u = (lon / (2 * np.pi) + 0.5) * tex_w + spheres.texture_offsets[i]
            texel_v = (0.5 - lat / np.pi) * (tex_h - 1)
            image[front] = _lookup(spheres.texture, texel_u, texel_v, wrap=True) * shade[:, None]
    return np.clip(image, 0, 255).astype(np.uint8), depth, object_id
