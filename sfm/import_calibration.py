"""`dynrecon import-calibration`: static, board-calibrated cameras instead of SfM.

Reads a Qualisys QCA XML or a Pose2Sim/anipose TOML calibration and writes `cameras.json` where every decoded
frame of each video gets its camera's one static pose.

Conventions (checked on ../shared/data/videos/pose2sim_demo, see tests/sfm/test_import_calibration.py):
- QCA `<transform>`: x, y, z is the camera centre in the world, in mm; the matrix r_ij, read row by row, is
  the cam_from_world rotation of Qualisys' camera axes (y up, z backwards), so OpenCV's is diag(1,-1,-1) @ r.
  Intrinsics are in sensor sub-pixels: focal lengths and principal point / 64 give pixels (of the fov_video
  window). Distortion coefficients are used as they are (OpenCV k1, k2, p1, p2, k3 on normalized coordinates).
- TOML `[cam_N]`: `rotation` (Rodrigues) and `translation` are OpenCV's cam_from_world (as aniposelib's
  Camera.rvec/tvec and Pose2Sim's calib.toml), translation in metres; `matrix` is K in pixels; `size` [w, h].
"""

from __future__ import annotations

import enum
import logging
import re
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from dynrecon.errors import InputError
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras
from sfm.video import VideoInfo, probe_video

log = logging.getLogger(__name__)

QCA_SUBPIXELS = 64.0
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])  # flips the y and z camera axes


class CalibrationFormat(enum.Enum):
    AUTO = "auto"
    QCA = "qca"
    TOML = "toml"


@dataclass(kw_only=True)
class StaticCamera:
    """One calibrated camera. R, t: cam_from_world (OpenCV), t in metres; K, dist: OpenCV pixels."""

    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (4,) or (5,)
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass(kw_only=True)
class ImportOptions:
    format: CalibrationFormat = CalibrationFormat.AUTO
    scale: float = 1.0  # multiplies the world coordinates (after conversion to metres)


# ----------------------------------------------------------------------------------------------------------
# Readers


def _attr(element: ET.Element, key: str, path: Path, where: str) -> float:
    value = element.get(key)
    if value is None:
        raise InputError(path, f'missing attribute "{key}"', where=where, fix="is this a Qualisys .qca file?")
    try:
        return float(value)
    except ValueError:
        raise InputError(path, f'attribute "{key}" = {value!r} is not a number', where=where) from None


def read_qca(path: str | Path) -> list[StaticCamera]:
    """Qualisys QCA XML: one StaticCamera per `<camera>`, in file order."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except ET.ParseError as error:
        raise InputError(path, f"not valid XML: {error}") from None
    cameras = []
    for index, element in enumerate(root.iter("camera")):
        name = element.get("serial") or f"camera{index + 1}"
        where = f"camera {name!r}"
        transform, intrinsic = element.find("transform"), element.find("intrinsic")
        fov = element.find("fov_video")
        if transform is None or intrinsic is None:
            raise InputError(path, "camera lacks <transform> or <intrinsic>", where=where)
        left = top = 0.0
        if fov is not None:
            left, top = _attr(fov, "left", path, where), _attr(fov, "top", path, where)
            width = round(_attr(fov, "right", path, where) - left + 1)
            height = round(_attr(fov, "bottom", path, where) - top + 1)
        else:
            width = round(_attr(intrinsic, "sensorMaxU", path, where) / QCA_SUBPIXELS) + 1
            height = round(_attr(intrinsic, "sensorMaxV", path, where) / QCA_SUBPIXELS) + 1
        M = np.array([[_attr(transform, f"r{i}{j}", path, where) for j in (1, 2, 3)] for i in (1, 2, 3)])
        center = np.array([_attr(transform, key, path, where) for key in "xyz"]) / 1000.0
        R = QUALISYS_TO_OPENCV @ M
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise InputError(path, "transform r11..r33 is not a rotation", where=where)
        R = _orthonormalize(R)
        fx = _attr(intrinsic, "focalLengthU", path, where) / QCA_SUBPIXELS
        fy = _attr(intrinsic, "focalLengthV", path, where) / QCA_SUBPIXELS
        cx = _attr(intrinsic, "centerPointU", path, where) / QCA_SUBPIXELS - left
        cy = _attr(intrinsic, "centerPointV", path, where) / QCA_SUBPIXELS - top
        skew = float(intrinsic.get("skew", "0") or 0) / QCA_SUBPIXELS
        K = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        dist = np.array(
            [
                _attr(intrinsic, key, path, where)
                for key in (
                    "radialDistortion1",
                    "radialDistortion2",
                    "tangentalDistortion1",
                    "tangentalDistortion2",
                    "radialDistortion3",
                )
            ]
        )
        cameras.append(
            StaticCamera(name=name, width=width, height=height, K=K, dist=dist, R=R, t=-R @ center)
        )
    if not cameras:
        raise InputError(path, "no <camera> element found", fix="is this a Qualisys .qca file?")
    return cameras


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation: calibration files store 16 digits or fewer, cameras.json checks to 1e-5."""
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _toml_array(section: dict, key: str, shape: tuple[int, ...], path: Path, where: str) -> np.ndarray:
    if key not in section:
        raise InputError(
            path, f'missing key "{key}"', where=where, fix="see the Pose2Sim/anipose calib.toml layout"
        )
    try:
        value = np.asarray(section[key], dtype=float)
    except (TypeError, ValueError):
        raise InputError(path, f'"{key}" must be numbers', where=where) from None
    if value.shape != shape:
        raise InputError(path, f'"{key}" has shape {value.shape}, expected {shape}', where=where)
    if not np.all(np.isfinite(value)):
        raise InputError(path, f'"{key}" contains NaN or infinity', where=where)
    return value


def read_toml(path: str | Path) -> list[StaticCamera]:
    """Pose2Sim/anipose calib.toml: one StaticCamera per table that has a `matrix` (skips `[metadata]`)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise InputError(path, f"not valid TOML: {error}") from None
    cameras = []
    for key, section in data.items():
        if not isinstance(section, dict) or "matrix" not in section:
            continue
        where = f"[{key}]"
        name = str(section.get("name", key))
        if section.get("fisheye", False):
            raise InputError(
                path,
                "fisheye cameras are not supported (cameras.json holds OpenCV pinhole distortion)",
                where=where,
                fix="undistort the videos first, or calibrate as pinhole",
            )
        size = _toml_array(section, "size", (2,), path, where)
        K = _toml_array(section, "matrix", (3, 3), path, where)
        dist = np.asarray(section.get("distortions", [0.0, 0.0, 0.0, 0.0]), dtype=float).ravel()
        if dist.shape not in ((4,), (5,)):
            raise InputError(path, f'"distortions" has {dist.size} values, expected 4 or 5', where=where)
        rvec = _toml_array(section, "rotation", (3,), path, where)
        tvec = _toml_array(section, "translation", (3,), path, where)
        R = cv2.Rodrigues(rvec)[0]
        cameras.append(
            StaticCamera(name=name, width=round(size[0]), height=round(size[1]), K=K, dist=dist, R=R, t=tvec)
        )
    if not cameras:
        raise InputError(
            path,
            "no camera table (with a `matrix`) found",
            fix="expected [cam_1] name, size, matrix, distortions, rotation, translation",
        )
    return cameras


def write_toml(path: str | Path, cameras: list[StaticCamera]) -> Path:
    """Write a Pose2Sim/anipose calib.toml (for round-trip tests, and to hand poses to those tools)."""
    lines = []
    for index, camera in enumerate(cameras, start=1):
        rvec = cv2.Rodrigues(camera.R)[0].ravel()

        def row(values: np.ndarray) -> str:
            return "[ " + ", ".join(repr(float(v)) for v in values) + ",]"

        lines += [
            f"[cam_{index}]",
            f'name = "{camera.name}"',
            f"size = [ {camera.width}, {camera.height},]",
            "matrix = [ " + ", ".join(row(r) for r in camera.K) + ",]",
            f"distortions = {row(camera.dist)}",
            f"rotation = {row(rvec)}",
            f"translation = {row(camera.t)}",
            "fisheye = false",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    path = Path(path)
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def read_calibration(path: str | Path, fmt: CalibrationFormat = CalibrationFormat.AUTO) -> list[StaticCamera]:
    path = Path(path)
    if fmt is CalibrationFormat.AUTO:
        lower = path.name.lower()
        if lower.endswith(".toml"):
            fmt = CalibrationFormat.TOML
        elif ".qca" in lower or lower.endswith(".xml"):
            fmt = CalibrationFormat.QCA
        else:
            raise InputError(
                path,
                "cannot tell the calibration format from the name",
                fix="pass --format qca or --format toml",
            )
    return read_qca(path) if fmt is CalibrationFormat.QCA else read_toml(path)


# ----------------------------------------------------------------------------------------------------------
# Matching calibrated cameras to videos


def _normalized(name: str) -> str:
    """'cam_01', 'Cam1', 'cam01' all become 'cam1': calibration tools and users spell numbers differently."""
    return re.sub(r"\d+", lambda m: str(int(m.group())), re.sub(r"[^0-9a-z]", "", name.lower()))


def match_cameras(cameras: list[StaticCamera], videos: list[VideoInfo], path: Path) -> list[StaticCamera]:
    """The camera for each video: by name (ignoring case, separators and leading zeros), else by order."""
    by_name = {_normalized(c.name): c for c in cameras}
    matched = [by_name.get(_normalized(v.name)) for v in videos]
    if all(m is not None for m in matched) and len({id(m) for m in matched}) == len(videos):
        return [m for m in matched if m is not None]
    if len(cameras) == len(videos):
        log.warning(
            "%s: camera names %s do not match video names %s; matching them in the given order",
            path,
            [c.name for c in cameras],
            [v.name for v in videos],
        )
        return list(cameras)
    raise InputError(
        path,
        f"{len(cameras)} cameras ({', '.join(c.name for c in cameras)}) cannot be matched "
        f"to {len(videos)} videos ({', '.join(v.name for v in videos)})",
        fix="name each video after its camera, or give one video per camera in the file's order",
    )


def run(
    calibration: str | Path,
    videos: Sequence[str | Path],
    out_dir: str | Path,
    options: ImportOptions | None = None,
) -> Path:
    """Write `out_dir/cameras.json`: every decoded frame of each video with its camera's static pose."""
    options = options or ImportOptions()
    calibration = Path(calibration)
    if not videos:
        raise InputError(calibration, "no videos given", fix="list the videos the calibration belongs to")
    infos = [probe_video(v) for v in tqdm(videos, desc="probing videos", unit="video", leave=False)]
    names = [info.name for info in infos]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise InputError(
            infos[names.index(duplicates[0])].path,
            f"video name {duplicates[0]!r} is used twice",
            fix="video names (file names without extension) must be unique",
        )
    cameras = match_cameras(read_calibration(calibration, options.format), infos, calibration)
    result = CameraSet()
    for info, camera in zip(infos, cameras, strict=True):
        if (info.width, info.height) != (camera.width, camera.height):
            log.warning(
                "%s is %dx%d but camera %r was calibrated at %dx%d; intrinsics are used unchanged",
                info.path,
                info.width,
                info.height,
                camera.name,
                camera.width,
                camera.height,
            )
        frames = [
            FrameCamera(
                frame=i,
                time=float(time),
                K=camera.K.copy(),
                R=camera.R.copy(),
                t=camera.t * options.scale,
                dist=camera.dist.copy(),
            )
            for i, time in enumerate(info.times)
        ]
        result.videos.append(
            VideoCameras(name=info.name, width=info.width, height=info.height, fps=info.fps, frames=frames)
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = write_cameras(out / "cameras.json", result)
    log.info("wrote %s: %d videos, %d frames", path, len(result.videos), result.num_frames)
    return path
