"""`cameras.json`: every posed frame of every video, in one world frame (see docs/formats.md).

R, t are cam_from_world (x_cam = R X + t, COLMAP's convention). Pixel coordinates follow OpenCV: the centre of the
top-left pixel is (0, 0). `frame` is the 0-based index of the decoded frame in its video; frames without a pose are
absent.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import InputError
from dynrecon.readers import check_frame, read_json

log = logging.getLogger(__name__)

ROTATION_TOLERANCE = 1e-5
# Plausibility limits: finite values beyond them are typos or corrupt files that would silently spoil a solve.
FOCAL_RANGE_PX = (1.0, 1e6)  # fx, fy: below 1 px is a field of view near 180 degrees at any image size
MAX_PRINCIPAL_PX = 1e6  # |cx|, |cy| and the skew
MAX_TRANSLATION = 1e9  # each |t| component, world units (1000 km in mm)
MAX_DISTORTION = 1e3  # |k1|, |k2|, |p1|, |p2|, |k3|, ...
# OpenCV's distortion vectors read: 4 or 5 coefficients, or 8 of its rational model (CALIB_RATIONAL_MODEL)
DIST_SHAPES = ((4,), (5,), (8,))
DIST_FORMS = "[k1, k2, p1, p2], [k1, k2, p1, p2, k3] or [k1, k2, p1, p2, k3, k4, k5, k6]"
MAX_SECONDS = 1e10  # |time| and |clock_offset|: Unix epoch times fit (about 1.8e9 s today), 1e300 does not
# Times per frame this many times off the video's fps: warned (a timelapse's real capture times, frame numbers given
# as times), and refused within MILLISECONDS of 1000x (times in milliseconds).
FPS_WARNED = 10.0
MILLISECONDS = (300.0, 3000.0)


@dataclass(kw_only=True)
class FrameCamera:
    """The camera of one decoded frame."""

    frame: int
    K: np.ndarray  # (3, 3) intrinsics, pixels, OpenCV convention
    R: np.ndarray  # (3, 3) rotation cam_from_world
    t: np.ndarray  # (3,) translation cam_from_world
    time: float | None = None  # seconds from the video's start, as the decoder reports it
    dist: np.ndarray | None = None  # (4,), (5,) or (8,): OpenCV k1, k2, p1, p2[, k3[, k4, k5, k6]]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,)."""
        return -self.R.T @ self.t


@dataclass(kw_only=True)
class VideoCameras:
    name: str
    width: int
    height: int
    fps: float | None = None
    frames: list[FrameCamera] = field(default_factory=list)
    # Seconds, global time = own time + clock_offset: the clock the subject path of `register` found (None: unknown).
    clock_offset: float | None = None
    # The user declared clock_offset (--synchronized, --offsets: a trigger, a clap, a timecode), not an estimate:
    # where the solve's own clocks agree with it, it is used (docs/refinement.md).
    clock_declared: bool = False
    # The video's own person numbers (points person<N>_<keypoint>) -> the number of that person across videos
    # (`register` matched them: sfm/subject/people.py); None: the tracks' names are used as they are.
    people: dict[int, int] | None = None

    def frame_numbers(self) -> np.ndarray:
        return np.array([f.frame for f in self.frames], dtype=np.int64)


@dataclass(kw_only=True)
class CameraSet:
    videos: list[VideoCameras] = field(default_factory=list)

    def video(self, name: str) -> VideoCameras:
        for video in self.videos:
            if video.name == name:
                return video
        raise KeyError(name)

    @property
    def num_frames(self) -> int:
        return sum(len(v.frames) for v in self.videos)


# ---------------------------------------------------------------------------------------------------------------
# Writing


def _frame_to_json(frame: FrameCamera) -> dict[str, Any]:
    entry: dict[str, Any] = {"frame": int(frame.frame)}
    if frame.time is not None:
        entry["time"] = float(frame.time)
    entry["K"] = np.asarray(frame.K, dtype=float).tolist()
    entry["R"] = np.asarray(frame.R, dtype=float).tolist()
    entry["t"] = np.asarray(frame.t, dtype=float).tolist()
    if frame.dist is not None:
        entry["dist"] = np.asarray(frame.dist, dtype=float).tolist()
    return entry


def cameras_to_json(cameras: CameraSet) -> dict[str, Any]:
    return {
        "videos": [
            {
                "name": video.name,
                "fps": None if video.fps is None else float(video.fps),
                "width": int(video.width),
                "height": int(video.height),
                "frames": [_frame_to_json(f) for f in sorted(video.frames, key=lambda f: f.frame)],
            }
            | ({} if video.clock_offset is None else {"clock_offset": float(video.clock_offset)})
            | ({"clock_declared": True} if video.clock_declared and video.clock_offset is not None else {})
            | ({} if video.people is None else {"people": {str(k): int(v) for k, v in sorted(video.people.items())}})
            for video in cameras.videos
        ]
    }


def write_cameras(path: str | Path, cameras: CameraSet) -> Path:
    """Write `cameras.json` atomically. Raises InputError when the content would not read back."""
    path = Path(path)
    validate_cameras(cameras, path)
    atomic_write_text(path, json.dumps(cameras_to_json(cameras), indent=1) + "\n")
    return path


# ---------------------------------------------------------------------------------------------------------------
# Reading


def read_cameras(path: str | Path) -> CameraSet:
    """Read and validate `cameras.json`; every problem is an InputError naming the video and frame."""
    path = Path(path)
    data = read_json(
        path,
        missing_fix="run `dynrecon register` or give the right path",
        fix="give the cameras.json that register or import-calibration wrote",
    )
    cameras = cameras_from_json(data, path)
    validate_cameras(cameras, path)
    return cameras


def cameras_from_json(data: Any, path: Path | None = None) -> CameraSet:
    if not isinstance(data, dict) or not isinstance(data.get("videos"), list):
        raise InputError(
            path, 'top level must be an object with a list "videos"', fix="see docs/formats.md#camerasjson"
        )
    videos = []
    for vi, vdata in enumerate(data["videos"]):
        where = f"videos[{vi}]"
        if not isinstance(vdata, dict):
            raise InputError(path, "each video must be an object", where=where)
        for key in ("name", "width", "height", "frames"):
            if key not in vdata:
                raise InputError(path, f'missing key "{key}"', where=where, fix="see docs/formats.md#camerasjson")
        name = vdata["name"]
        if not isinstance(name, str) or not name:
            raise InputError(path, '"name" must be a non-empty string', where=where)
        where = f"video {name!r}"
        fps = vdata.get("fps")
        if fps is not None and (not _finite_number(fps) or fps <= 0):
            raise InputError(path, f'"fps" must be a positive number or null, got {repr(fps)[:40]}', where=where)
        width, height = vdata["width"], vdata["height"]
        if not (isinstance(width, int) and isinstance(height, int) and 0 < width < 2**31 and 0 < height < 2**31):
            raise InputError(
                path,
                f'"width" and "height" must be positive integers below 2^31, got '
                f"{repr(width)[:40]}x{repr(height)[:40]}",
                where=where,
            )
        if not isinstance(vdata["frames"], list):
            raise InputError(path, '"frames" must be a list', where=where)
        clock_offset = vdata.get("clock_offset")
        if clock_offset is not None and not _finite_number(clock_offset):
            raise InputError(
                path, f'"clock_offset" must be a finite number or absent, got {repr(clock_offset)[:40]}', where=where
            )
        declared = vdata.get("clock_declared", False)
        if not isinstance(declared, bool):
            raise InputError(path, f'"clock_declared" must be true or false, got {repr(declared)[:40]}', where=where)
        if declared and clock_offset is None:
            raise InputError(
                path, '"clock_declared" is true but there is no "clock_offset"', where=where, fix="give the offset"
            )
        people = _people_from_json(vdata.get("people"), path, where)
        frames = [_frame_from_json(fdata, path, f"{where} frames[{fi}]") for fi, fdata in enumerate(vdata["frames"])]
        videos.append(
            VideoCameras(
                name=name,
                fps=None if fps is None else float(fps),
                width=width,
                height=height,
                frames=frames,
                clock_offset=None if clock_offset is None else float(clock_offset),
                clock_declared=declared,
                people=people,
            )
        )
    return CameraSet(videos=videos)


def _people_from_json(value: Any, path: Path | None, where: str) -> dict[int, int] | None:
    """`"people": {"<own number>": <number across videos>, ...}` (absent: None)."""
    if value is None:
        return None
    ok = isinstance(value, dict) and all(
        isinstance(k, str) and k.isascii() and k.isdigit() and isinstance(v, int) and not isinstance(v, bool) and v >= 0
        for k, v in value.items()
    )
    if not ok:
        raise InputError(
            path, f'"people" must map person numbers to person numbers, got {repr(value)[:60]}', where=where
        )
    mapped = {int(k): int(v) for k, v in value.items()}
    if len(set(mapped.values())) != len(mapped):
        raise InputError(path, f'"people" maps two people of the video onto one: {repr(value)[:60]}', where=where)
    return mapped


def _finite_number(value: Any) -> bool:
    """A JSON int or float that is finite as a float (math.isfinite overflows on huge ints)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _matrix(value: Any, shape: tuple[int, ...], key: str, path: Path | None, where: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond the float range
        raise InputError(path, f'"{key}" must be numbers of shape {shape}', where=where) from None
    if array.shape != shape:
        raise InputError(path, f'"{key}" has shape {array.shape}, expected {shape}', where=where)
    if not np.all(np.isfinite(array)):
        raise InputError(path, f'"{key}" contains NaN or infinity', where=where, fix="drop frames without a valid pose")
    return array


def _frame_from_json(fdata: Any, path: Path | None, where: str) -> FrameCamera:
    if not isinstance(fdata, dict):
        raise InputError(path, "each frame must be an object", where=where)
    for key in ("frame", "K", "R", "t"):
        if key not in fdata:
            raise InputError(path, f'missing key "{key}"', where=where, fix="see docs/formats.md#camerasjson")
    number = fdata["frame"]
    if not isinstance(number, int) or isinstance(number, bool) or number < 0:
        raise InputError(path, f'"frame" must be a non-negative integer, got {repr(number)[:40]}', where=where)
    check_frame(number, path, where, name='"frame"')
    where = f"{where.rsplit(' ', 1)[0]} frame {number}"
    time = fdata.get("time")
    if time is not None and not _finite_number(time):
        raise InputError(path, f'"time" must be a finite number, got {repr(time)[:40]}', where=where)
    dist = fdata.get("dist")
    if dist is not None:
        try:
            dist_array = np.asarray(dist, dtype=float) if isinstance(dist, list) else None
        except (TypeError, ValueError, OverflowError):
            dist_array = None
        if dist_array is None or dist_array.shape not in DIST_SHAPES or not np.all(np.isfinite(dist_array)):
            raise InputError(path, f'"dist" must be {DIST_FORMS}', where=where)
        dist = dist_array
    return FrameCamera(
        frame=number,
        time=None if time is None else float(time),
        K=_matrix(fdata["K"], (3, 3), "K", path, where),
        R=_matrix(fdata["R"], (3, 3), "R", path, where),
        t=_matrix(fdata["t"], (3,), "t", path, where),
        dist=dist,
    )


def validate_cameras(cameras: CameraSet, path: Path | None = None) -> None:
    """Check the geometric sanity of every frame: proper rotations, usable intrinsics, unique names/frames; and
    that decoder times increase with the frame number, in seconds."""
    if not _clearly_valid(cameras):
        _check_frames(cameras, path)
    for video in cameras.videos:  # after the frames: a frame given twice is named as such
        check_times(video, path)


def not_a_rotation(R: np.ndarray) -> str | None:
    """None for a rotation (orthonormal within ROTATION_TOLERANCE, det +1), else how far it is from one."""
    with np.errstate(over="ignore", invalid="ignore"):  # a huge R overflows to inf: refused
        orthogonality = float(np.abs(R @ R.T - np.eye(3)).max())
    if orthogonality > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        return f"|R R^T - I| = {orthogonality:.2g}, det = {np.linalg.det(R):.3g}"
    return None


def _check_frames(cameras: CameraSet, path: Path | None) -> None:
    """Frame by frame: the first frame at fault is named."""
    seen_names: set[str] = set()
    for video in cameras.videos:
        if video.name in seen_names:
            raise InputError(path, f"video name {video.name!r} appears twice", fix="video names must be unique")
        seen_names.add(video.name)
        seen_frames: set[int] = set()
        for frame in video.frames:
            where = f"video {video.name!r} frame {frame.frame}"
            if frame.frame in seen_frames:
                raise InputError(path, "frame appears twice", where=where, fix="keep one pose per frame")
            seen_frames.add(frame.frame)
            wrong = not_a_rotation(frame.R)
            if wrong is not None:
                raise InputError(
                    path,
                    f'"R" is not a rotation ({wrong})',
                    where=where,
                    fix="R must be the orthonormal cam_from_world rotation with det +1",
                )
            K = frame.K
            if (
                K[0, 0] <= 0
                or K[1, 1] <= 0
                or abs(K[2, 2] - 1) > 1e-9
                or np.any(np.abs(K[2, :2]) > 1e-12)
                or abs(K[1, 0]) > 1e-12
            ):
                raise InputError(path, '"K" must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0', where=where)
            check_plausible(frame.K, frame.t, frame.dist, path, where)


# Warnings about times already given in this process.
_TIMES_WARNED: set[str] = set()


def check_times(video: VideoCameras, path: Path | None = None) -> None:
    """Refuse a video's decoder times that cannot be seconds from its start: not increasing with the frame number
    (the solve would order its frames wrongly), beyond MAX_SECONDS, or about 1000 times its fps's period
    (milliseconds; other ratios from FPS_WARNED are warned)."""
    where = f"video {video.name!r}"
    if video.clock_offset is not None and abs(video.clock_offset) >= MAX_SECONDS:
        raise InputError(
            path,
            f'"clock_offset" {video.clock_offset:.6g} s is implausible',
            where=where,
            fix=f"clock offsets are seconds below {MAX_SECONDS:g} in magnitude",
        )
    timed = sorted((f.frame, f.time) for f in video.frames if f.time is not None)
    if not timed:
        return
    frames = np.array([frame for frame, _ in timed], dtype=float)
    times = np.array([time for _, time in timed], dtype=float)
    huge = np.flatnonzero(np.abs(times) >= MAX_SECONDS)
    if huge.size:
        raise InputError(
            path,
            f'"time" {times[huge[0]]:.6g} s is implausible',
            where=f"{where} frame {int(frames[huge[0]])}",
            fix=f"decoder times are seconds from the video's start, below {MAX_SECONDS:g}",
        )
    steps = np.diff(times)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        i = int(back[0])
        raise InputError(
            path,
            f'"time" {times[i + 1]:.6g} s is not after frame {int(frames[i])}\'s {times[i]:.6g} s',
            where=f"{where} frame {int(frames[i + 1])}",
            fix='decoder times must increase with the frame number; remove the "time" fields of a video whose '
            "times are unknown (its clock is then estimated)",
        )
    if video.fps is None or len(times) < 3:
        return
    per_frame = float(np.median(steps / np.maximum(np.diff(frames), 1.0)))
    ratio = per_frame * video.fps
    if 1.0 / FPS_WARNED < ratio < FPS_WARNED:
        return
    error = InputError(
        path,
        f'its "time"s step by {per_frame:.6g} s per frame (median), {ratio:.3g} times the {1.0 / video.fps:.6g} s '
        f'of its "fps" {video.fps:g}',
        where=where,
        fix='decoder times are in seconds (not milliseconds or frames); or fix "fps" (null when unknown)',
    )
    if MILLISECONDS[0] < ratio < MILLISECONDS[1]:
        raise error
    message = f"{error}; the times are used as given"
    if message not in _TIMES_WARNED:  # one file is read by several steps of a run: said once
        _TIMES_WARNED.add(message)
        log.warning(message)


def _clearly_valid(cameras: CameraSet) -> bool:
    """Whether every check of `validate_cameras` passes with room to spare, tested on all frames at once: then it
    raises nothing. False sends it through its frame-by-frame checks, which name the first frame at fault (the
    rotation test's batched products may differ from those in the last bits, hence the margins)."""
    names = [video.name for video in cameras.videos]
    frames = [frame for video in cameras.videos for frame in video.frames]
    if len(set(names)) != len(names) or any(
        len({frame.frame for frame in video.frames}) != len(video.frames) for video in cameras.videos
    ):
        return False
    if not frames:
        return True
    try:
        K = np.array([frame.K for frame in frames], dtype=float)
        R = np.array([frame.R for frame in frames], dtype=float)
        t = np.array([frame.t for frame in frames], dtype=float)
        dist = np.concatenate([np.ravel(frame.dist) for frame in frames if frame.dist is not None] or [np.zeros(0)])
    except (TypeError, ValueError):
        return False
    if K.shape[1:] != (3, 3) or R.shape[1:] != (3, 3) or t.shape[1:] != (3,):
        return False
    if not (np.isfinite(K).all() and np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(dist).all()):
        return False
    with np.errstate(over="ignore", invalid="ignore"):  # a huge R overflows to inf: not plausible
        orthogonality = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    low, high = FOCAL_RANGE_PX
    focal = K[:, [0, 1], [0, 1]]
    return bool(
        np.all(orthogonality < 0.5 * ROTATION_TOLERANCE)
        and np.all(np.linalg.det(R) > 0.5)
        and np.all(np.abs(K[:, 2, 2] - 1) <= 1e-9)
        and np.all(np.abs(K[:, 2, :2]) <= 1e-12)
        and np.all(np.abs(K[:, 1, 0]) <= 1e-12)
        and np.all((focal >= low) & (focal < high))
        and np.all(np.abs(K[:, [0, 0, 1], [1, 2, 2]]) < MAX_PRINCIPAL_PX)
        and np.all(np.abs(t) < MAX_TRANSLATION)
        and np.all(np.abs(dist) < MAX_DISTORTION)
    )


def check_plausible(
    K: np.ndarray, t: np.ndarray | None, dist: np.ndarray | None, path: Path | None, where: str
) -> None:
    """Refuse finite values that no camera has: focal lengths, principal point, translation, distortion."""
    for name, value in (("K", K), ("t", t), ("dist", dist)):
        if value is not None and not np.all(np.isfinite(value)):
            raise InputError(path, f'"{name}" contains NaN or infinity', where=where)
    if abs(K[2, 2] - 1) > 1e-9 or np.any(np.abs(K[2, :2]) > 1e-12) or abs(K[1, 0]) > 1e-12:
        raise InputError(
            path,
            f'"K" {np.asarray(K).tolist()} is not a camera matrix',
            where=where,
            fix="it must read [[fx, s, cx], [0, fy, cy], [0, 0, 1]]",
        )
    low, high = FOCAL_RANGE_PX
    for name, focal in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not low <= focal < high:
            raise InputError(
                path,
                f'"K" {name} = {focal:.6g} px is implausible',
                where=where,
                fix=f"focal lengths are in pixels, between {low:g} and {high:g}",
            )
    if max(abs(K[0, 1]), abs(K[0, 2]), abs(K[1, 2])) >= MAX_PRINCIPAL_PX:
        raise InputError(
            path,
            f'"K" principal point ({K[0, 2]:.6g}, {K[1, 2]:.6g}) or skew {K[0, 1]:.6g} is implausible',
            where=where,
            fix=f"they are in pixels, below {MAX_PRINCIPAL_PX:g} in magnitude",
        )
    if t is not None and float(np.max(np.abs(t))) >= MAX_TRANSLATION:  # not the norm: it overflows near 1e308
        raise InputError(
            path,
            f'"t" {np.asarray(t).tolist()} is implausible',
            where=where,
            fix=f"translations are below {MAX_TRANSLATION:g} world units",
        )
    if dist is not None and np.any(np.abs(dist) >= MAX_DISTORTION):
        raise InputError(
            path,
            f'"dist" {np.asarray(dist).tolist()} is implausible',
            where=where,
            fix=f"OpenCV distortion coefficients are below {MAX_DISTORTION:g} in magnitude",
        )
