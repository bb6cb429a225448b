"""Calibration files, and the `dynrecon import-calibration` stage (`run`): static, board-calibrated cameras
instead of SfM.

Reads a Qualisys QCA XML or a TOML calibration (Pose2Sim/anipose/FreeMoCap `[cam_N]`, caliscope's
`camera_array.toml` `[cameras.N]` and its `config.toml` `[cam_N]`) and writes `cameras.json` where every decoded
frame of each video gets its camera's one static pose.

Conventions (checked on ../shared/data/videos/pose2sim_demo, see tests/sfm/test_import_calibration.py):
- QCA `<transform>`: x, y, z is the camera centre in the world, in mm; the matrix r_ij, read row by row, is
  the cam_from_world rotation of Qualisys' camera axes (y up, z backwards), so OpenCV's is diag(1,-1,-1) @ r.
  Intrinsics are in sensor sub-pixels: focal lengths and principal point / 64 give pixels (of the fov_video
  window). Distortion coefficients are used as they are (OpenCV k1, k2, p1, p2, k3 on normalized coordinates).
- TOML `[cam_N]`: `rotation` (Rodrigues) and `translation` are OpenCV's cam_from_world (as aniposelib's
  Camera.rvec/tvec and Pose2Sim's calib.toml), translation in metres; `matrix` is K in pixels; `size` [w, h].
- caliscope (checked on ../shared/data/videos/caliscope_office, see tests/sfm/test_import_calibration.py):
  `camera_array.toml` has `[cameras.0]`, `[cameras.1]`..., its `config.toml` `[cam_0]`...: the same keys with
  `cam_id`, `rotation` a 3x3 cam_from_world matrix (OpenCV), `translation` in metres; `ignore = true` cameras
  are left out; cameras are named `cam_<cam_id>` (its videos are cam_0.mp4...). A camera with intrinsics only
  (no rotation/translation yet) is read with R = t = None: `register --intrinsics` can use it, `run` refuses it.
- `rotation` may be a Rodrigues 3-vector or a 3x3 matrix (9 numbers) in every TOML layout.
- DANNCE / Label3D `.mat` files (`sfm/calibration_dannce.py`): no image size, so width = height = 0 (the
  video's own size is taken).
- DLT coefficients (DLTdv / easyWand `*_dltCoefs.csv`, Argus `*-dlt-coefficients.csv`, `sfm/calibration_dlt.py`):
  no image size, distortion only from a camera profile (`--profile`); translations in the calibration object's
  units (the spread rule below).
- FreeMoCap's `*_camera_calibration.toml` is anipose's layout with translations in millimetres (its charuco
  square size is given in mm). Units rule (`Units.AUTO`): millimetres when the `[metadata]` table has
  `charuco_square_size` (FreeMoCap) or `square_length` (sleap-anipose), or when the cameras are over MM_SPREAD
  units apart (anipose's own files give the board's unit, mm in its documentation), else metres; `--units m|mm`
  overrides it.
"""

from __future__ import annotations

import logging
import math
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from dynrecon.atomic import require_writable
from dynrecon.errors import InputError
from dynrecon.names import first_repeated, holds_name, numbered_name, spelled_alike, within_name
from dynrecon.readers import read_text, shown
from sfm.calibration_dannce import is_dannce, read_dannce
from sfm.calibration_dlt import dlt_cameras, dlt_sizes, is_dlt
from sfm.cameras import (
    DIST_FORMS,
    DIST_SHAPES,
    CameraSet,
    FrameCamera,
    VideoCameras,
    check_plausible,
    read_cameras,
    write_cameras,
)
from sfm.options import CalibrationFormat, DltPixels, ImportCalibrationOptions, Units, declared_offsets
from sfm.video import ProbedVideo, probe_video
from sfm.video_standin import stand_in_videos, with_size

log = logging.getLogger(__name__)

QCA_SUBPIXELS = 64.0
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])  # flips the y and z camera axes
FREEMOCAP_MM_KEY = "charuco_square_size"  # in FreeMoCap's [metadata]: the board's square size in mm
# [metadata] keys that give the board's square in mm, so the translations are mm: FreeMoCap's, sleap-anipose's
MM_KEYS = (FREEMOCAP_MM_KEY, "square_length")
# Without such a key: cameras further apart than this many units are a rig measured in mm (anipose's calibrations
# use the board's unit, mm in its documentation); a rig this many metres across is a stadium, not a lab.
MM_SPREAD = 100.0
UNSURE_SPREAD = 10.0  # between this and MM_SPREAD units: metres, but said (a close-up rig in mm is as likely)
MOVING_FIX = "register those videos together with this recording's, or leave that camera's video out"
_UNIT_WARNINGS: set[tuple[str, float]] = set()
SAME_POSE = 1e-6  # a static camera's frames share one pose: rotation and translation equal to this (relative)


@dataclass(kw_only=True)
class StaticCamera:
    """One calibrated camera. R, t: cam_from_world (OpenCV), t in metres, both None for an intrinsics-only
    calibration; K, dist: OpenCV pixels; width = height = 0 where the file gives no image size (the video's)."""

    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (4,), (5,) or (8,): OpenCV's
    R: np.ndarray | None  # (3, 3)
    t: np.ndarray | None  # (3,)
    no_pose: str | None = None  # why R and t are None, where the file says (default: intrinsics only)
    # K[1, 2] still lacks the image height (a DLT whose rows count up from the bottom: the file gives no height);
    # intrinsics_at_video_size adds the video's
    cy_plus_height: bool = False
    # other names the file gives the camera (caliscope's older sessions: `port = N` of [cam_N], videos port_N.mp4)
    aliases: tuple[str, ...] = ()

    @property
    def has_pose(self) -> bool:
        return self.R is not None and self.t is not None

    def pose(self, path: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(R, t); an InputError naming the camera when the file gives it no pose."""
        if (self.R is None or self.t is None) and self.no_pose is not None:
            raise InputError(path, self.no_pose, where=f"camera {self.name!r}", fix=MOVING_FIX)
        if self.R is None or self.t is None:
            raise InputError(
                path,
                f"camera {self.name!r} has intrinsics only (no rotation/translation)",
                where=f"camera {self.name!r}",
                fix="calibrate the extrinsics first (caliscope: the capture volume step), or leave its video out",
            )
        return self.R, self.t

    @property
    def center(self) -> np.ndarray:
        R, t = self.pose()
        return -R.T @ t


# ----------------------------------------------------------------------------------------------------------
# Readers


def _attr(element: ET.Element, key: str, path: Path, where: str, default: float | None = None) -> float:
    value = element.get(key)
    if value is None or (default is not None and not value.strip()):
        if default is not None:
            return default
        raise InputError(path, f'missing attribute "{key}"', where=where, fix="is this a Qualisys .qca file?")
    try:
        number = float(value)
    except ValueError:
        raise InputError(path, f'attribute "{key}" = {value!r} is not a number', where=where) from None
    if not math.isfinite(number):
        raise InputError(path, f'attribute "{key}" = {value!r} is not a finite number', where=where)
    return number


def read_qca(path: str | Path) -> list[StaticCamera]:
    """Qualisys QCA XML: one StaticCamera per `<camera>`, in file order."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except ET.ParseError as error:
        raise InputError(path, f"not valid XML: {error}") from None
    except OSError as error:
        raise InputError(path, f"not a readable file ({error.strerror or error})", fix="give the .qca file") from None
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
        skew = _attr(intrinsic, "skew", path, where, default=0.0) / QCA_SUBPIXELS
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
        cameras.append(StaticCamera(name=name, width=width, height=height, K=K, dist=dist, R=R, t=-R @ center))
    if not cameras:
        raise InputError(path, "no <camera> element found", fix="is this a Qualisys .qca file?")
    return cameras


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation: calibration files store 16 digits or fewer, cameras.json checks to 1e-5."""
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _toml_array(section: dict, key: str, shape: tuple[int, ...], path: Path, where: str) -> np.ndarray:
    if key not in section:
        raise InputError(path, f'missing key "{key}"', where=where, fix="see the Pose2Sim/anipose calib.toml layout")
    if _has_bool(section[key]):  # float(True) is 1.0: a typo would become a focal length of one pixel
        raise InputError(path, f'"{key}" must be numbers, not true/false', where=where)
    try:
        value = np.asarray(section[key], dtype=float)
    except (TypeError, ValueError):
        raise InputError(path, f'"{key}" must be numbers', where=where) from None
    if value.shape != shape:
        raise InputError(path, f'"{key}" has shape {value.shape}, expected {shape}', where=where)
    if not np.all(np.isfinite(value)):
        raise InputError(path, f'"{key}" contains NaN or infinity', where=where)
    return value


def _has_bool(value: object) -> bool:
    return isinstance(value, bool) or (isinstance(value, list) and any(_has_bool(v) for v in value))


def _toml_flag(section: dict, key: str, path: Path, where: str) -> bool:
    value = section.get(key, False)
    if not isinstance(value, bool):
        raise InputError(path, f"{key} = {value!r} must be true or false", where=where)
    return value


def _toml_rotation(section: dict, path: Path, where: str) -> np.ndarray:
    """`rotation` as a Rodrigues 3-vector or a 3x3 matrix (nested or 9 flat numbers), checked and orthonormalized."""
    try:
        if _has_bool(section["rotation"]):
            raise ValueError("true/false")
        value = np.asarray(section["rotation"], dtype=float)
    except (TypeError, ValueError):
        raise InputError(path, '"rotation" must be numbers', where=where) from None
    if not np.all(np.isfinite(value)):
        raise InputError(path, '"rotation" contains NaN or infinity', where=where)
    if value.size == 3:
        return np.asarray(cv2.Rodrigues(value.reshape(3, 1))[0], dtype=float)
    if value.size != 9:
        raise InputError(
            path,
            f'"rotation" has shape {value.shape}, expected a Rodrigues vector (3,) or a matrix (3, 3)',
            where=where,
        )
    R = value.reshape(3, 3)
    if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise InputError(path, '"rotation" is a 3x3 matrix but not a rotation', where=where)
    return _orthonormalize(R)


def _toml_sections(data: dict) -> list[tuple[str, dict, str | None]]:
    """(where, table, caliscope cam_id or None) for every camera table of any known layout."""
    sections: list[tuple[str, dict, str | None]] = []
    for key, section in data.items():
        if not isinstance(section, dict):
            continue
        if key == "cameras" and all(isinstance(v, dict) for v in section.values()):  # caliscope camera_array
            sections += [(f"[cameras.{k}]", v, str(v.get("cam_id", k))) for k, v in section.items()]
        elif "matrix" in section or "cam_id" in section or ("name" in section and CAMERA_KEYS.intersection(section)):
            cam_id = section.get("cam_id")
            sections.append((f"[{key}]", section, None if cam_id is None else str(cam_id)))
    return sections


def toml_units(data: dict, units: Units = Units.AUTO) -> float:
    """Metres per translation unit: `units`, or for AUTO mm when `[metadata]` gives the board's square in mm
    (FreeMoCap's `charuco_square_size`, sleap-anipose's `square_length`), else metres (`read_toml` then checks
    the cameras' spread)."""
    if units is Units.AUTO:
        metadata = data.get("metadata")
        sizes = [metadata.get(k) for k in MM_KEYS] if isinstance(metadata, dict) else []
        # a square of 1 or more units is mm (a metre-wide square is no board); 0.024 would be metres
        in_mm = any(isinstance(v, int | float) and not isinstance(v, bool) and v >= 1 for v in sizes)
        units = Units.MM if in_mm else Units.M
    return 0.001 if units is Units.MM else 1.0


def _spread(cameras: list[StaticCamera]) -> float:
    """The largest distance between two camera centres (0 with fewer than two posed cameras)."""
    centres = [camera.center for camera in cameras if camera.has_pose]
    return max((float(np.linalg.norm(a - b)) for i, a in enumerate(centres) for b in centres[i + 1 :]), default=0.0)


# A table with a name and any of these is a camera, with or without its `matrix` (warned about when without).
CAMERA_KEYS = frozenset({"size", "distortions", "rotation", "translation"})


def read_toml(path: str | Path, units: Units = Units.AUTO) -> list[StaticCamera]:
    """Every TOML layout: one StaticCamera per camera table (see the module doc), translations in metres.

    Tables without a `matrix` are skipped (caliscope: not yet calibrated, with a warning; `[metadata]`,
    `[charuco]`... silently), as are caliscope cameras with `ignore = true`.
    """
    path = Path(path)
    text = read_text(path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise InputError(path, f"not valid TOML: {error}") from None
    except RecursionError:
        raise InputError(path, "not valid TOML: nested too deeply") from None
    metres = toml_units(data, units)
    if metres != 1.0:
        log.info("%s: translations read in millimetres", path)
    cameras = []
    for where, section, cam_id in _toml_sections(data):
        if _toml_flag(section, "ignore", path, where):
            log.info("%s: %s has ignore = true; skipped", path, where)
            continue
        if "matrix" not in section:
            log.warning("%s: %s has no intrinsics (`matrix`); skipped", path, where)
            continue
        name = str(section["name"]) if "name" in section else f"cam_{cam_id}" if cam_id is not None else where[1:-1]
        if _toml_flag(section, "fisheye", path, where):
            raise InputError(
                path,
                "fisheye cameras are not supported (cameras.json holds OpenCV pinhole distortion)",
                where=where,
                fix="undistort the videos first, or calibrate as pinhole",
            )
        if section.get("rotation_count", 0):
            log.warning(
                "%s: %s has rotation_count = %s; the calibration is used in the videos' stored orientation",
                path,
                where,
                section["rotation_count"],
            )
        size = _toml_array(section, "size", (2,), path, where)
        K = _toml_array(section, "matrix", (3, 3), path, where)
        try:
            dist = np.asarray(section.get("distortions", [0.0, 0.0, 0.0, 0.0]), dtype=float).ravel()
        except (TypeError, ValueError, OverflowError):
            raise InputError(path, '"distortions" must be 4, 5 or 8 numbers', where=where) from None
        if dist.shape not in DIST_SHAPES:
            raise InputError(
                path,
                f'"distortions" has {dist.size} values, expected 4, 5 or 8 (OpenCV\'s {DIST_FORMS})',
                where=where,
                fix="undistort the tracks first and give zero distortion, or calibrate with OpenCV's 4, 5 or 8 "
                "coefficients",
            )
        R: np.ndarray | None = None
        t: np.ndarray | None = None
        if "rotation" in section or "translation" in section:
            if "rotation" not in section or "translation" not in section:
                raise InputError(path, "has one of rotation / translation but not the other", where=where)
            R = _toml_rotation(section, path, where)
            t = _toml_array(section, "translation", (3,), path, where) * metres
        port = section.get("port")
        aliases = (f"port_{port}",) if isinstance(port, int) and not isinstance(port, bool) else ()
        cameras.append(
            StaticCamera(
                name=name, width=round(size[0]), height=round(size[1]), K=K, dist=dist, R=R, t=t, aliases=aliases
            )
        )
    if not cameras:
        raise InputError(
            path,
            "no camera table (with a `matrix`) found",
            fix="expected [cam_1] (or caliscope's [cameras.0]) with size, matrix, distortions, rotation, translation",
        )
    if metres == 1.0:
        _units_by_spread(cameras, path, units)
    return cameras


def _units_by_spread(cameras: list[StaticCamera], path: Path, units: Units) -> None:
    """With no unit given (AUTO): translations in mm where the cameras are over MM_SPREAD units apart (a lab rig
    in mm; turned into metres here), said when the reading is unsure."""
    spread = _spread(cameras)
    if units is Units.AUTO and spread > UNSURE_SPREAD:  # no unit given, and metres are unsure
        in_mm = spread > MM_SPREAD
        read, other = ("millimetres", "metres") if in_mm else ("metres", "millimetres")
        said = (str(path), round(spread, 6))
        if said not in _UNIT_WARNINGS:  # registration reads the file in several steps: one warning per file
            _UNIT_WARNINGS.add(said)
            log.warning(
                "%s: the cameras are up to %.0f units apart: translations read in %s (--units %s if they are %s)",
                path,
                spread,
                read,
                "m" if in_mm else "mm",
                other,
            )
        if in_mm:
            for camera in cameras:
                camera.t = None if camera.t is None else camera.t * 0.001


def write_toml(path: str | Path, cameras: list[StaticCamera]) -> Path:
    """Write a Pose2Sim/anipose calib.toml (for round-trip tests, and to hand poses to those tools)."""
    lines = []
    for index, camera in enumerate(cameras, start=1):
        R, t = camera.pose(Path(path))
        rvec = cv2.Rodrigues(R)[0].ravel()

        def row(values: np.ndarray) -> str:
            return "[ " + ", ".join(repr(float(v)) for v in values) + ",]"

        lines += [
            f"[cam_{index}]",
            f'name = "{camera.name}"',
            f"size = [ {camera.width}, {camera.height},]",
            "matrix = [ " + ", ".join(row(r) for r in camera.K) + ",]",
            f"distortions = {row(camera.dist)}",
            f"rotation = {row(rvec)}",
            f"translation = {row(t)}",
            "fisheye = false",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    path = Path(path)
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def read_cameras_json(path: str | Path) -> list[StaticCamera]:
    """The cameras of dynrecon's `cameras.json` (another recording by the same cameras, e.g. a board filmed
    before the session): one per video, its first frame's intrinsics and distortion; a pose only where every
    frame has the same one (a static camera), else intrinsics only (`no_pose` says why)."""
    path = Path(path)
    cameras = []
    for video in read_cameras(path).videos:
        if not video.frames:
            log.warning("%s: video %r has no posed frame (that recording's registration left it out)", path, video.name)
            continue
        first = video.frames[0]
        R, t = first.R, first.t
        scale = max(1.0, float(np.abs(t).max()))
        moving = any(
            np.abs(f.R - R).max() > SAME_POSE or np.abs(f.t - t).max() > SAME_POSE * scale for f in video.frames
        )
        cameras.append(
            StaticCamera(
                name=video.name,
                width=video.width,
                height=video.height,
                K=first.K.copy(),
                dist=np.zeros(4) if first.dist is None else first.dist.copy(),
                R=None if moving else R.copy(),
                t=None if moving else t.copy(),
                no_pose=f"video {video.name!r}'s camera moves in this recording: its poses fit no other video"
                if moving
                else None,
            )
        )
    if not cameras:
        raise InputError(path, "no video has a posed frame", fix="give the cameras.json of a registered recording")
    return cameras


def read_calibration(
    path: str | Path,
    fmt: CalibrationFormat = CalibrationFormat.AUTO,
    units: Units = Units.AUTO,
    pixels: DltPixels = DltPixels.AUTO,
    profile: str | Path | None = None,
) -> list[StaticCamera]:
    """Cameras of a QCA, TOML, cameras.json, DANNCE or DLT file; TOML cameras may lack a pose (R = t = None): see
    StaticCamera.pose. `pixels`: a DLT file's pixel convention; `profile`: its camera profile (the lenses)."""
    path = Path(path)
    if fmt is CalibrationFormat.AUTO:
        lower = path.name.lower()
        if is_dlt(path):  # before DANNCE's .mat: easyWand's *_easyWandData.mat holds DLT coefficients
            fmt = CalibrationFormat.DLT
        elif is_dannce(path):
            fmt = CalibrationFormat.DANNCE
        elif lower.endswith(".toml"):
            fmt = CalibrationFormat.TOML
        elif lower.endswith(".json"):
            fmt = CalibrationFormat.CAMERAS_JSON
        elif ".qca" in lower or lower.endswith(".xml"):
            fmt = CalibrationFormat.QCA
        else:
            raise InputError(
                path,
                "cannot tell the calibration format from the name",
                fix="name it .toml, .qca.txt, .xml, .json, .mat or *_dltCoefs.csv; import-calibration also takes "
                "--format qca, toml, json, dannce or dlt",
            )
    if profile is not None and fmt is not CalibrationFormat.DLT:
        raise InputError(Path(profile), f"--profile is a DLT file's camera profile; {path.name} is a {fmt.value} file")
    if fmt is CalibrationFormat.CAMERAS_JSON:
        return read_cameras_json(path)  # read_cameras has checked it
    if fmt is CalibrationFormat.DANNCE:
        cameras = [
            StaticCamera(name=c.name, width=0, height=0, K=c.K, dist=c.dist, R=c.R, t=c.t)
            for c in read_dannce(path, mm=units is not Units.M)
        ]
    elif fmt is CalibrationFormat.DLT:
        decomposed = dlt_cameras(path, pixels, profile)
        sizes = dlt_sizes(path) or [(0, 0)] * len(decomposed)  # DLT text files give no size
        cameras = []
        for (name, K, R, t, up, dist), (w, h) in zip(decomposed, sizes, strict=True):
            if up and h > 0:  # rows up from the bottom of a known height: the row of K is known now
                K = K.copy()
                K[1, 2] += h
                up = False
            cameras.append(StaticCamera(name=name, width=w, height=h, K=K, dist=dist, R=R, t=t, cy_plus_height=up))
        if units is Units.MM:
            for camera in cameras:
                camera.t = camera.pose()[1] * 0.001
        elif units is Units.AUTO:
            _units_by_spread(cameras, path, units)
    else:
        cameras = read_qca(path) if fmt is CalibrationFormat.QCA else read_toml(path, units)
    for camera in cameras:
        where = f"camera {shown(camera.name)}"
        sizeless = fmt in (CalibrationFormat.DANNCE, CalibrationFormat.DLT) and camera.width == camera.height == 0
        if not sizeless and not (0 < camera.width < 2**31 and 0 < camera.height < 2**31):
            raise InputError(path, f"image size {camera.width}x{camera.height} is not positive", where=where)
        check_plausible(camera.K, camera.t, camera.dist, path, where)
        if camera.R is not None and not np.all(np.isfinite(camera.R)):
            raise InputError(path, "rotation contains NaN or infinity", where=where)
    twice = first_repeated(camera.name for camera in cameras)
    if twice is not None:  # videos are matched to cameras by name: two of one name match one video
        raise InputError(
            path,
            f"two cameras are named {shown(cameras[twice].name)}",
            fix="give every camera its own name (a copied table?)",
        )
    return cameras


# ----------------------------------------------------------------------------------------------------------
# Matching calibrated cameras to videos


def camera_named(cameras: list[StaticCamera], name: str) -> StaticCamera | None:
    """The camera named `name` exactly, else the one camera whose name matches it when case, separators, leading
    zeros and a video suffix are ignored (None when several do: cam1 with both cam01 and cam_1), else the one
    camera whose name begins or ends the video's (minimal_back.mp4 for `back`: a session's prefix), else the one
    camera the file also names so (`StaticCamera.aliases`: caliscope's port_1.mp4 for `port = 1`)."""
    names = [c.name for c in cameras]
    found = spelled_alike(name, names) or within_name(name, names)
    if len(found) == 1:
        return next(c for c in cameras if c.name == found[0])
    if not found:  # a name the file gives besides the camera's own (caliscope's port_N)
        aliases = {alias: camera for camera in cameras for alias in camera.aliases}
        alike = spelled_alike(name, list(aliases))
        return aliases[alike[0]] if len(alike) == 1 else None
    return None


def match_cameras(cameras: list[StaticCamera], videos: list[ProbedVideo], path: Path) -> list[StaticCamera]:
    """The camera for each video: by name (ignoring case, separators and leading zeros), else, when no name matches
    at all, by cameras named around every video's name, else by order; some names matching and others not is an
    error (an order would give the matched cameras to other videos)."""
    matched = [camera_named(cameras, v.name) for v in videos]
    if all(m is None for m in matched):
        for rule in (holds_name, numbered_name):  # the video named around the camera's name, or cam10 for '10'
            found = [rule(v.name, [c.name for c in cameras]) for v in videos]
            chosen = [next(c for c in cameras if c.name == f[0]) if len(f) == 1 else None for f in found]
            if all(m is not None for m in chosen) and len({id(m) for m in chosen}) == len(videos):
                return [m for m in chosen if m is not None]  # every video, each its own camera: else as before
    if all(m is not None for m in matched) and len({id(m) for m in matched}) == len(videos):
        return [m for m in matched if m is not None]
    if any(m is not None for m in matched):
        unmatched = [v.name for v, m in zip(videos, matched, strict=True) if m is None]
        taken = {id(m) for m in matched if m is not None}
        left = [c.name for c in cameras if id(c) not in taken]
        detail = f"videos {', '.join(unmatched)} match no camera name" if unmatched else "two videos match one camera"
        raise InputError(
            path,
            f"{detail} (cameras left: {', '.join(left) or 'none'}), while other videos match by name",
            fix="name each video after its camera (e.g. cam_1.mp4 for [cam_1]), or rename the cameras in the file",
        )
    if len(cameras) == len(videos):
        log.warning(
            "%s: camera names %s do not match video names %s; matching them in the given order (`dynrecon solve` "
            "checks that order against the tracks)",
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


SAME_ASPECT = 0.002  # width and height scale alike within this fraction: the video is the calibrated image resized
# The video's sides are the calibrated ones swapped within this fraction: turned, letterboxed or not (Pose2Sim's
# 1080x1920 videos of a 1088x1920 calibration differ by 0.74 %), unless the calibrated image is nearly square.
TURNED_ASPECT = 0.01
NEAR_SQUARE = 0.05
_SIZE_WARNINGS: set[tuple[str, str, int, int]] = set()


class VideoSizeError(InputError):
    """The calibrated intrinsics cannot be this video's: its size says it is not the calibrated image."""


class TurnedVideoError(VideoSizeError):
    """The video is the calibrated image turned by 90 degrees (portrait against landscape)."""


def intrinsics_at_video_size(
    K: np.ndarray, size: tuple[int, int], video: ProbedVideo, name: str, cy_plus_height: bool = False
) -> np.ndarray:
    """K (3, 3) of camera `name`, calibrated at `size` (width, height), in `video`'s pixels: unchanged at the
    calibrated size; scaled where the video is the calibrated image resized (one scale for both axes: a phone
    calibrated at 4K filming at 1080p); otherwise unchanged, with a warning, since a crop or a padding cannot be
    told from the sizes alone. TurnedVideoError where the video is the calibrated image turned by 90 degrees
    (or resized and turned): the turn's direction is not in the sizes, and K unchanged would be wrong. A size of
    (0, 0) (the file gives none) takes the video's, if the principal point lies in it; `cy_plus_height`: K's
    principal point row still lacks the image height (StaticCamera.cy_plus_height), the video's is added."""
    width, height = size
    if cy_plus_height:
        K = K.astype(float).copy()
        K[1, 2] += video.height
    if (width, height) in ((0, 0), (video.width, video.height)):  # the video is the calibrated image
        cx, cy = K[0, 2], K[1, 2]
        outside = not (0 <= cx < video.width and 0 <= cy < video.height)  # a loose calibration's, used as it is
        said = (str(video.path), name, -1, -1)
        if outside and said not in _SIZE_WARNINGS:  # registration reads the intrinsics in several steps
            _SIZE_WARNINGS.add(said)
            log.warning(
                "%s: camera %s: principal point (%.1f, %.1f) outside this %dx%d video; used as the file gives "
                "it (check that each video is given with its own camera)",
                video.path,
                name,
                cx,
                cy,
                video.width,
                video.height,
            )
        return K
    turned = abs(video.width / height - video.height / width) <= TURNED_ASPECT * video.width / height
    if abs(width / height - 1.0) > NEAR_SQUARE and turned:
        raise TurnedVideoError(
            video.path,
            f"is {video.width}x{video.height}, camera {name!r} was calibrated at {width}x{height}: the video is "
            "the calibrated image turned by 90 degrees (portrait against landscape)",
            fix="calibrate the camera in the video's orientation, or leave it out of the calibration file",
        )
    sx, sy = video.width / width, video.height / height
    sizes = f"{video.path} is {video.width}x{video.height}, camera {name!r} was calibrated at {width}x{height}"
    if abs(sx - sy) <= SAME_ASPECT * max(sx, sy):
        K = K.astype(float).copy()
        # pixel centres sit at integer coordinates in OpenCV: x' = (x + 0.5) s - 0.5
        K[0, 0], K[0, 1], K[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
        log.info("%s: its intrinsics are scaled by %.4g", sizes, sx)
        return K
    cx, cy = K[0, 2], K[1, 2]
    if not (0 <= cx < video.width and 0 <= cy < video.height):  # not a crop or a padding of the calibrated image
        raise VideoSizeError(
            video.path,
            f"is {video.width}x{video.height}, camera {name!r} was calibrated at {width}x{height} and its principal "
            f"point ({cx:.0f}, {cy:.0f}) lies outside this video: it is not the calibrated image",
            fix="give the video the camera filmed at its calibrated size, or leave the camera out of the file",
        )
    said = (str(video.path), name, width, height)
    if said in _SIZE_WARNINGS:  # registration reads the intrinsics in several steps: one warning per video
        return K
    _SIZE_WARNINGS.add(said)
    log.warning(
        "%s (another aspect ratio: a crop, a padding or a rotation); its intrinsics are used unchanged, so check "
        "that the video is the calibrated camera's full image",
        sizes,
    )
    return K


def _refuse_repeated_poses(cameras: list[StaticCamera], poses: list[tuple[np.ndarray, np.ndarray]], path: Path) -> None:
    """Two cameras at one pose are one camera given twice (a copied table): every point seen by both would be
    triangulated from a zero baseline, silently wrong."""
    for i, (Ri, ti) in enumerate(poses):
        for j in range(i + 1, len(poses)):
            Rj, tj = poses[j]
            scale = max(1.0, float(np.abs(ti).max()), float(np.abs(tj).max()))
            if np.abs(Ri - Rj).max() < 1e-9 and np.abs(ti - tj).max() < 1e-9 * scale:
                raise InputError(
                    path,
                    f"cameras {cameras[i].name!r} and {cameras[j].name!r} have the same pose: one camera given "
                    "twice (a copied table?)",
                    where=f"camera {cameras[j].name!r}",
                    fix="calibrate that camera again, or leave its video out; register --intrinsics still takes the "
                    "file's intrinsics",
                )


def run(
    calibration: str | Path,
    videos: Sequence[str | Path],
    out_dir: str | Path,
    options: ImportCalibrationOptions | None = None,
) -> Path:
    """Write `out_dir/cameras.json`: every decoded frame of each video with its camera's static pose."""
    options = options or ImportCalibrationOptions()
    calibration = Path(calibration)
    if not (math.isfinite(options.scale) and 1e-6 <= options.scale <= 1e6):
        raise InputError(
            None,
            f"--scale {options.scale:g}: the world's scale factor must be a positive number (1e-6 to 1e6)",
            fix="leave --scale out for the file's metres, or give e.g. --scale 1000 for millimetres",
        )
    if not videos:
        raise InputError(calibration, "no videos given", fix="list the videos the calibration belongs to")
    require_writable(out_dir)
    # the file first: a mistake in it is said before every video is probed (seconds each)
    calibrated = read_calibration(calibration, options.format, options.units, options.pixels, options.profile)
    tracks = options.tracks or (Path(out_dir) / "tracks.csv")
    given = options.tracks is not None or options.size is not None
    stand_ins = stand_in_videos(videos, tracks, options.fps, given)
    infos = [
        stand_in or probe_video(v)
        for v, stand_in in tqdm(
            zip(videos, stand_ins, strict=True), total=len(videos), desc="probing videos", unit="video", leave=False
        )
    ]
    names = [info.name for info in infos]
    twice = first_repeated(names)
    if twice is not None:
        raise InputError(
            infos[twice].path,
            f"video name {names[twice]!r} is used twice",
            fix="video names (file names without extension) must be unique",
        )
    spans = {info.name: info.span for info in infos if info.num_frames}
    offsets = declared_offsets(options.synchronized, options.offsets, names, spans)
    cameras = match_cameras(calibrated, infos, calibration)
    for info, stand_in, camera in zip(infos, stand_ins, cameras, strict=True):
        if stand_in is not None:
            with_size(info, (camera.width, camera.height), options.size, calibration)
    poses = [camera.pose(calibration) for camera in cameras]  # refuses intrinsics-only cameras, naming them
    _refuse_repeated_poses(cameras, poses, calibration)
    result = CameraSet()
    for info, camera, (R, t) in zip(infos, cameras, poses, strict=True):
        K = intrinsics_at_video_size(camera.K, (camera.width, camera.height), info, camera.name, camera.cy_plus_height)
        frames = [
            FrameCamera(
                frame=i,
                time=None if info.stand_in else float(time),  # --fps's rate, not measured: the solve tests it
                K=K.copy(),
                R=R.copy(),
                t=t * options.scale,
                dist=camera.dist.copy(),
            )
            for i, time in enumerate(info.times)
        ]
        result.videos.append(
            VideoCameras(
                name=info.name,
                width=info.width,
                height=info.height,
                fps=info.fps,
                frames=frames,
                clock_offset=offsets.get(info.name),
                clock_declared=info.name in offsets,
            )
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = write_cameras(out / "cameras.json", result)
    log.info("wrote %s: %d videos, %d frames", path, len(result.videos), result.num_frames)
    if len(result.videos) < 2:
        log.warning("%s holds one video: `dynrecon solve` needs two or more (give every camera's video)", path)
    return path


__all__ = [
    "CalibrationFormat",
    "DltPixels",
    "ImportCalibrationOptions",
    "StaticCamera",
    "TurnedVideoError",
    "Units",
    "VideoSizeError",
    "intrinsics_at_video_size",
    "match_cameras",
    "read_calibration",
    "read_cameras_json",
    "read_qca",
    "read_toml",
    "run",
    "toml_units",
    "write_toml",
]
