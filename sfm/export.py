"""From a COLMAP model to dynrecon's files: OpenCV intrinsics in original pixels, and the coloured point
cloud."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from dynrecon.atomic import atomic_open
from sfm.frames import Resize

# COLMAP model name -> how its params map to OpenCV (fx, fy, cx, cy) and dist [k1, k2, p1, p2(, k3(, k4, k5, k6))].
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def opencv_intrinsics(camera: pycolmap.Camera, resize: Resize) -> tuple[np.ndarray, np.ndarray | None]:
    """(K (3, 3), dist (4,)/(5,)/(8,) or None) in the original video's pixels, OpenCV pixel convention.

    COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at (0, 0); and SfM ran on frames
    resized
    by `resize.scale`, so a continuous coordinate u_colmap_small = scale * (u_opencv + 0.5)."""
    p = np.asarray(camera.params, dtype=float)
    model = camera.model_name
    dist: np.ndarray | None = None
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = np.array([p[3], 0.0, 0.0, 0.0])
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = np.array([p[3], p[4], 0.0, 0.0])
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        dist = p[4:8].copy()
    elif model == "FULL_OPENCV":  # k1, k2, p1, p2, k3, k4, k5, k6: OpenCV's rational model, in its order
        fx, fy, cx, cy = p[:4]
        dist = p[4:12].copy() if np.any(p[9:12] != 0) else p[4:9].copy()
    else:
        raise ValueError(f"camera model {model} is not supported; use one of {', '.join(SUPPORTED_MODELS)}")
    s = resize.scale
    K = np.array([[fx / s, 0.0, cx / s - 0.5], [0.0, fy / s, cy / s - 0.5], [0.0, 0.0, 1.0]])
    return K, dist


def colmap_params(K: np.ndarray, dist: np.ndarray | None, resize: Resize) -> tuple[str, list[float]]:
    """Known OpenCV intrinsics (original pixels) as a COLMAP camera model and params for the resized
    frames."""
    s = resize.scale
    fx, fy = K[0, 0] * s, K[1, 1] * s
    cx, cy = (K[0, 2] + 0.5) * s, (K[1, 2] + 0.5) * s
    d = np.zeros(8) if dist is None else np.concatenate([np.asarray(dist, float), np.zeros(8)])[:8]
    if np.any(d[4:] != 0):
        return "FULL_OPENCV", [fx, fy, cx, cy, *d]
    return "OPENCV", [fx, fy, cx, cy, *d[:4]]


def image_reprojection_errors(rec: pycolmap.Reconstruction, image: pycolmap.Image) -> np.ndarray:
    """(N,) reprojection errors (SfM pixels) of the image's observations that have a 3D point."""
    observed = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in image.points2D if p.has_point3D()]
    if not observed:
        return np.zeros(0)
    xy = np.array([o[0] for o in observed])
    xyz = np.array([o[1] for o in observed])
    pose = image.cam_from_world()
    in_cam = xyz @ pose.rotation.matrix().T + pose.translation
    camera = rec.cameras[image.camera_id]
    projected = camera.img_from_cam(in_cam)
    return np.linalg.norm(projected - xy, axis=1)


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY: float32 x, y, z and uint8 red, green, blue per vertex.

    xyz: (N, 3) world coordinates; rgb: (N, 3) uint8."""
    vertex = np.empty(
        len(xyz),
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    for i, key in enumerate("xyz"):
        vertex[key] = xyz[:, i]
    for i, key in enumerate(("red", "green", "blue")):
        vertex[key] = rgb[:, i]
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment dynrecon background (static SfM points)\n"
        f"element vertex {len(xyz)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with atomic_open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(vertex.tobytes())


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read back what `write_ply` wrote: (xyz (N, 3) float, rgb (N, 3) uint8)."""
    data = open(path, "rb").read()  # noqa: SIM115
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int(
        next(line for line in data[:end].decode("ascii").splitlines() if line.startswith("element vertex")).split()[-1]
    )
    vertex = np.frombuffer(
        data[end:],
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
        count=count,
    )
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(float)
    rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1)
    return xyz, rgb
