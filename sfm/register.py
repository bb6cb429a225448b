"""`dynrecon register`: a pose and intrinsics for every frame of every video, in one world frame.

Stages: probe videos -> test each camera for motion (`sfm.static`) -> SfM images: a static video sends one
background image (temporal median), a moving one sampled frames (+ masks) -> SIFT (one camera per video) ->
matching of sequential pairs within a video and of every keyframe / background image across videos -> mapping
(incremental or global), keep the largest model -> a static video's frames take its background image's pose, a
moving video's other frames are posed by PnP against the model -> static videos the background left out are
posed from the moving subject's 2D tracks (`sfm.subject`, anchored on the videos the background posed) ->
cameras.json, background.ply, register_report.json (which path posed each video, and why).
pycolmap stages run in child processes (`sfm.isolated`) so that a fatal COLMAP error is a clear message.
"""

from __future__ import annotations

import enum
import logging
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from dynrecon.errors import DynreconError, InputError
from sfm import colmap_steps
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras, write_cameras
from sfm.export import write_ply
from sfm.frames import JPEG_QUALITY, Resize, image_name, select_frames, write_frames
from sfm.intrinsics import known_intrinsics
from sfm.isolated import run_isolated
from sfm.localize_frames import localize_all
from sfm.masks import mask_from_points, track_points, user_mask, write_mask
from sfm.pairs import build_pairs
from sfm.plan import FramePose, VideoPlan
from sfm.register_subject import pose_from_subject
from sfm.report import write_report
from sfm.static import StaticOptions, background_image, measure_motion, sample_frames
from sfm.video import VideoInfo, probe_video
from tracking.tracks import Tracks, read_tracks

log = logging.getLogger(__name__)


class Mapper(enum.Enum):
    INCREMENTAL = "incremental"
    GLOBAL = "global"


class Localize(enum.Enum):
    """Which frames besides the SfM frames get a pose by PnP."""

    AUTO = "auto"  # TRACKED when tracks exist, else ALL
    ALL = "all"
    TRACKED = "tracked"
    NONE = "none"


class CameraMotion(enum.Enum):
    """Whether a video's camera moves: measured per video (AUTO) or set by the user for all videos."""

    AUTO = "auto"
    STATIC = "static"
    MOVING = "moving"


class SubjectPath(enum.Enum):
    """When static videos are posed from the moving subject's tracks."""

    AUTO = "auto"  # for static videos the background did not pose, when tracks exist
    ALWAYS = "always"  # every static video, anchored on the background's poses where there are some
    NEVER = "never"


class RegistrationError(DynreconError):
    """SfM could not put at least two videos into one model."""


ALL_CORES = -1  # COLMAP's num_threads for one thread per core


@dataclass(kw_only=True)
class RegisterOptions:
    step: int = 0  # SfM frames: every Nth decoded frame (0: all, then thinned to max_frames)
    time_step: float | None = None  # or one frame per this many seconds (decoder timestamps)
    max_frames: int = 40  # SfM frames per video at most
    long_side: int = 1280  # SfM frames are resized to this long side (pixels)
    max_features: int = 4096  # SIFT features per frame
    # A static video's background image is matched across wide baselines: more features, DSP-SIFT with affine
    # shapes (see docs/registration.md).
    background_features: int = 16384
    camera_motion: CameraMotion = CameraMotion.AUTO
    static: StaticOptions = field(default_factory=StaticOptions)
    subject: SubjectPath = SubjectPath.AUTO
    scale: tuple[str, str, float] | None = None  # (point A, point B, metres) for the subject path's scale
    max_ratio: float = 0.8  # SIFT ratio test
    sequential_overlap: int = 5  # pairs (i, i+1..i+overlap) within a video
    keyframes: int = 10  # per video; every keyframe is matched with every keyframe of the other videos
    # Default by measurement (benchmarks/sfm_synthetic.py, sfm_pose2sim.py): global was slightly more accurate on
    # the synthetic room but put a camera at a wrong pose from false wide-baseline matches; incremental did not.
    mapper: Mapper = Mapper.INCREMENTAL
    camera_model: str = "SIMPLE_RADIAL"
    intrinsics: Path | None = None  # cameras.json / calib .toml / .qca with known intrinsics per video (fixed)
    tracks: Path | None = None  # tracks.csv for masks (default: WS/tracks.csv when it exists)
    masks: Path | None = None  # user masks folder (see sfm.masks)
    mask_radius: float = 40.0  # original pixels around tracked points
    use_masks: bool = True
    localize: Localize = Localize.AUTO
    min_inliers: int = 30  # PnP inliers needed to accept a localized frame
    init_min_inliers: int = 100  # two-view inliers the mapper needs for its initial pair (COLMAP default)
    num_threads: int = ALL_CORES


def _check_videos(videos: list[Path]) -> None:
    if len(videos) < 2:
        raise InputError(
            videos[0] if videos else None,
            "register needs at least two videos",
            fix="give every video of the scene",
        )
    names = [v.stem for v in videos]
    for video, name in zip(videos, names, strict=True):
        if names.count(name) > 1:
            raise InputError(
                video,
                f"video name {name!r} is used twice",
                fix="video names (file names without extension) must be unique",
            )


def _tracks(options: RegisterOptions, out: Path) -> Tracks | None:
    path = options.tracks or (out / "tracks.csv" if (out / "tracks.csv").exists() else None)
    return read_tracks(path) if path is not None else None


def _wanted_frames(info: VideoInfo, sfm_frames: np.ndarray, tracks: Tracks | None, mode: Localize) -> np.ndarray:
    if mode is Localize.AUTO:
        mode = Localize.TRACKED if tracks is not None else Localize.ALL
    if mode is Localize.ALL:
        extra = np.arange(info.num_frames)
    elif mode is Localize.TRACKED and tracks is not None:
        rows = np.array([v == info.name for v in tracks.video], dtype=bool)
        extra = np.unique(tracks.frame[rows])
        outside = extra[extra >= info.num_frames]
        if len(outside):
            raise InputError(
                tracks.path,
                f"video {info.name!r} has {info.num_frames} frames but tracks mention frame {int(outside[0])}",
                fix="tracks.csv belongs to other videos",
            )
    else:
        extra = np.zeros(0, np.int64)
    return np.union1d(sfm_frames, extra).astype(np.int64)


def _write_masks(videos: list[VideoPlan], tracks: Tracks | None, options: RegisterOptions, mask_dir: Path) -> int:
    """Masks for every frame that will have features extracted; returns how many were written."""
    written = 0
    for video in videos:
        per_frame = track_points(tracks, video.info.name) if tracks is not None else {}
        if tracks is not None and not per_frame:
            log.warning("no tracks for video %r: its frames are not masked", video.info.name)
        for frame in video.wanted:
            mask = user_mask(options.masks, video.info.name, int(frame), video.resize) if options.masks else None
            if int(frame) in per_frame:
                from_tracks = mask_from_points(per_frame[int(frame)], video.resize, options.mask_radius)
                mask = from_tracks if mask is None else np.minimum(mask, from_tracks)
            if mask is not None:
                write_mask(mask_dir, image_name(video.info.name, int(frame)), mask)
                written += 1
    return written


def _extract_args(
    videos: list[VideoPlan], names_of: dict[str, list[str]], intrinsics: dict[str, Any], options: RegisterOptions
) -> list[dict[str, Any]]:
    from sfm.export import colmap_params

    args = []
    for video in videos:
        model, params = options.camera_model, ""
        if video.info.name in intrinsics:
            K, dist = intrinsics[video.info.name]
            model, values = colmap_params(K, dist, video.resize)
            params = ",".join(repr(float(v)) for v in values)
        if names_of[video.info.name]:
            args.append(
                {
                    "name": video.info.name,
                    "images": names_of[video.info.name],
                    "camera_model": model,
                    "camera_params": params,
                    "max_features": options.background_features if video.static else options.max_features,
                    "wide_baseline": any(v.static for v in videos),  # one descriptor kind for all images
                }
            )
    return args


def run(videos: Sequence[str | Path], out_dir: str | Path, options: RegisterOptions | None = None) -> Path:
    """Register `videos` into one world frame; returns the path of the written `cameras.json`."""
    options = options or RegisterOptions()
    paths = [Path(v) for v in videos]
    _check_videos(paths)
    warnings: list[str] = []

    class _WarningCollector(logging.Handler):
        """Warnings (variable frame rate, unmasked videos, ...) also go into the report."""

        def emit(self, record: logging.LogRecord) -> None:
            warnings.append(record.getMessage())

    collector = _WarningCollector(level=logging.WARNING)
    for name in ("sfm.video", "sfm.masks", __name__):
        logging.getLogger(name).addHandler(collector)
    try:
        started = time.perf_counter()
        infos = [probe_video(p) for p in tqdm(paths, desc="probing videos", unit="video", leave=False)]
        timings: dict[str, float] = {"probe": time.perf_counter() - started}
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        for stale in ("cameras.json", "background.ply", "register_report.json"):
            (out / stale).unlink(missing_ok=True)  # never leave a previous run's result beside this report
        frames_dir, sfm_dir = out / "frames", out / "sfm"
        if sfm_dir.exists():
            shutil.rmtree(sfm_dir)
        sfm_dir.mkdir(parents=True)
        return _run(infos, out, frames_dir, sfm_dir, sfm_dir / "colmap.log", options, timings, warnings)
    finally:
        for name in ("sfm.video", "sfm.masks", __name__):
            logging.getLogger(name).removeHandler(collector)


def _plan_videos(infos: list[VideoInfo], tracks: Tracks | None, options: RegisterOptions) -> list[VideoPlan]:
    """Which frames each video sends to SfM and which need a pose; static or moving camera, measured."""
    videos = []
    for info in tqdm(infos, desc="testing camera motion", unit="video", leave=False):
        motion = None
        if options.camera_motion is CameraMotion.AUTO:
            motion = measure_motion(info, options.static)
            static = motion.static
            log.info("%s: %s", info.name, motion.reason)
        else:
            static = options.camera_motion is CameraMotion.STATIC
        resize = Resize.for_video(info, options.long_side)
        sfm_frames = (
            np.zeros(0, np.int64)
            if static
            else select_frames(info, step=options.step, time_step=options.time_step, max_frames=options.max_frames)
        )
        wanted = _wanted_frames(info, sfm_frames, tracks, options.localize)  # also checks the tracks' frames
        if static:  # a static video's pose costs nothing per frame: every frame gets it, whatever --localize says
            wanted = np.arange(info.num_frames, dtype=np.int64)
        videos.append(
            VideoPlan(
                info=info,
                resize=resize,
                sfm_frames=sfm_frames,
                wanted=wanted,
                motion=motion,
                static=static,
            )
        )
    return videos


def _write_background(
    video: VideoPlan, frames_dir: Path, tracks: Tracks | None, options: RegisterOptions, mask_dir: Path
) -> bool:
    """A static video's background image (and its mask where the subject stays); returns whether a mask was
    written."""
    frames = sample_frames(video.info, options.static.samples)
    image = background_image(video.info, frames, video.resize)
    path = frames_dir / video.background_name
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.jpg")
    cv2.imwrite(str(tmp), image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    tmp.replace(path)
    if not options.use_masks:
        return False
    masks = []
    if options.masks:
        user = user_mask(options.masks, video.info.name, int(frames[0]), video.resize)
        if user is not None:
            masks.append(user)
    per_frame = track_points(tracks, video.info.name) if tracks is not None else {}
    if per_frame:
        # The median image still shows the subject where it stayed for most of the sampled frames: mask there.
        known = np.array(sorted(per_frame))
        covered = [
            mask_from_points(per_frame[int(known[np.abs(known - f).argmin()])], video.resize, options.mask_radius) == 0
            for f in frames
        ]
        masks.append(np.where(np.mean(covered, axis=0) >= 0.5, 0, 255).astype(np.uint8))
    if not masks:
        return False
    write_mask(mask_dir, video.background_name, np.minimum.reduce(masks))
    return True


def _run(
    infos: list[VideoInfo],
    out: Path,
    frames_dir: Path,
    sfm_dir: Path,
    colmap_log: Path,
    options: RegisterOptions,
    timings: dict[str, float],
    warnings: list[str],
) -> Path:
    started = time.perf_counter()
    tracks = _tracks(options, out)
    intrinsics = known_intrinsics(options.intrinsics, infos) if options.intrinsics else {}
    videos = _plan_videos(infos, tracks, options)
    timings["motion_test"] = time.perf_counter() - started

    started = time.perf_counter()
    mask_dir = sfm_dir / "masks"
    names_of = {}
    masked = _write_masks([v for v in videos if not v.static], tracks, options, mask_dir) if options.use_masks else 0
    for video in videos:
        names_of[video.info.name] = write_frames(video.info, video.sfm_frames, frames_dir, video.resize)
        if video.static:
            masked += _write_background(video, frames_dir, tracks, options, mask_dir)
            names_of[video.info.name] = [video.background_name]
    timings["decode"] = time.perf_counter() - started

    database = sfm_dir / "database.db"
    started = time.perf_counter()
    keypoints = run_isolated(
        "feature extraction",
        colmap_steps.extract,
        {
            "database": str(database),
            "image_dir": str(frames_dir),
            "videos": _extract_args(videos, names_of, intrinsics, options),
            "mask_dir": str(mask_dir) if masked else None,
            "max_features": options.max_features,
            "num_threads": options.num_threads,
        },
        colmap_log,
    )
    timings["extract"] = time.perf_counter() - started
    for name, count in keypoints.items():
        if count < 50:
            warnings.append(f"{name}: only {count} SIFT features (untextured or blurred frame?)")

    started = time.perf_counter()
    pairs = build_pairs(names_of, overlap=options.sequential_overlap, keyframes=options.keyframes)
    matching = run_isolated(
        "matching",
        colmap_steps.match,
        {
            "database": str(database),
            "pairs": pairs,
            "max_ratio": options.max_ratio,
            "num_threads": options.num_threads,
        },
        colmap_log,
    )
    timings["match"] = time.perf_counter() - started

    started = time.perf_counter()
    model_dir = sfm_dir / "models"
    model_dir.mkdir()
    step = colmap_steps.map_global if options.mapper is Mapper.GLOBAL else colmap_steps.map_incremental
    fix_intrinsics = bool(intrinsics) and len(intrinsics) == len(videos)
    if intrinsics and not fix_intrinsics:
        warnings.append("known intrinsics for only some videos: all intrinsics are refined")
    models = run_isolated(
        f"mapping ({options.mapper.value})",
        step,
        {
            "database": str(database),
            "image_dir": str(frames_dir),
            "out_dir": str(model_dir),
            "fix_intrinsics": fix_intrinsics,
            "init_min_inliers": options.init_min_inliers,
            "num_threads": options.num_threads,
            "num_images": sum(len(n) for n in names_of.values()),
        },
        colmap_log,
    )
    timings["map"] = time.perf_counter() - started
    rec = None
    if models:
        best = max(models, key=lambda k: models[k])
        rec = pycolmap.Reconstruction(str(model_dir / best))
        if len(models) > 1:
            warnings.append(
                f"{len(models)} models; kept model {best} with {models[best]} images "
                f"(others: {', '.join(f'{k}: {v}' for k, v in models.items() if k != best)})"
            )
    else:
        warnings.append("background SfM found no model: no two images could be matched and triangulated")

    started = time.perf_counter()
    if rec is not None:
        results = localize_all(
            videos,
            rec,
            database,
            frames_dir,
            sfm_dir,
            mask_dir if masked else None,
            colmap_log,
            max_features=options.max_features,
            max_ratio=options.max_ratio,
            min_inliers=options.min_inliers,
            num_threads=options.num_threads,
        )
    else:
        results = {
            v.info.name: {int(f): FramePose(pose=None, reason="background SfM found no model") for f in v.wanted}
            for v in videos
        }
    timings["localize"] = time.perf_counter() - started

    started = time.perf_counter()
    subject_report = pose_from_subject(videos, results, tracks, intrinsics, options, warnings)
    timings["subject"] = time.perf_counter() - started

    registered_videos = [v for v in videos if any(r.pose is not None for r in results[v.info.name].values())]
    if len(registered_videos) < 2:
        names = ", ".join(v.info.name for v in registered_videos) or "none"
        _fail(
            out,
            videos,
            results,
            timings,
            warnings,
            options,
            pairs,
            matching,
            rec,
            subject_report,
            f"only {len(registered_videos)} of {len(videos)} videos registered ({names})",
        )

    started = time.perf_counter()
    cameras = CameraSet()
    clock_offsets = {c["name"]: c["offset_s"] for c in (subject_report or {}).get("cameras", [])}
    for video in registered_videos:
        frames = []
        for frame, result in sorted(results[video.info.name].items()):
            if result.pose is None or result.intrinsics is None:
                continue
            K, dist = result.intrinsics
            frames.append(
                FrameCamera(
                    frame=frame,
                    time=float(video.info.times[frame]),
                    K=K,
                    R=result.pose.rotation.matrix(),
                    t=np.asarray(result.pose.translation),
                    dist=dist,
                )
            )
        cameras.videos.append(
            VideoCameras(
                name=video.info.name,
                width=video.info.width,
                height=video.info.height,
                fps=video.info.fps,
                frames=frames,
                clock_offset=clock_offsets.get(video.info.name),
            )
        )
    if rec is not None:
        xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
        rgb = np.array([p.color for p in rec.points3D.values()], dtype=np.uint8).reshape(-1, 3)
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    write_ply(out / "background.ply", xyz, rgb)
    path = write_cameras(out / "cameras.json", cameras)
    timings["export"] = time.perf_counter() - started
    write_report(
        out / "register_report.json",
        videos=videos,
        results=results,
        timings=timings,
        warnings=warnings,
        options=options,
        pairs=len(pairs),
        matching=matching,
        rec=rec,
        subject=subject_report,
        error=None,
    )
    return path


def _fail(
    out: Path,
    videos: list[VideoPlan],
    results: dict[str, dict[int, FramePose]],
    timings: dict[str, float],
    warnings: list[str],
    options: RegisterOptions,
    pairs: list[tuple[str, str]],
    matching: dict[str, int],
    rec: pycolmap.Reconstruction | None,
    subject: dict[str, Any] | None,
    what: str,
) -> NoReturn:
    if subject is not None and subject.get("why"):
        hint = (
            f"the static videos share too little background, and the subject path could not pose them: {subject['why']}"
        )
    else:
        hint = (
            "try more overlap between the videos' views, more frames (--max-frames, --step), known intrinsics "
            "(--intrinsics), or --keyframes / --max-features higher"
        )
    message = f"{what}; cameras.json not written: {hint}. Details: {out / 'register_report.json'}"
    write_report(
        out / "register_report.json",
        videos=videos,
        results=results,
        timings=timings,
        warnings=warnings,
        options=options,
        pairs=len(pairs),
        matching=matching,
        rec=rec,
        subject=subject,
        error=message,
    )
    raise RegistrationError(message)


__all__ = [
    "CameraMotion",
    "Localize",
    "Mapper",
    "RegisterOptions",
    "RegistrationError",
    "SubjectPath",
    "read_cameras",
    "run",
]
