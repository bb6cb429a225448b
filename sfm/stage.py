"""`sfm.register` (`run` here): a pose and intrinsics for every frame of every video, in one world frame.

Stages: probe videos -> test each camera for motion (`sfm.static`) -> SfM images: a static video sends one
background image (temporal median), a moving one sampled frames (+ masks) -> SIFT (one camera per video) ->
matching of sequential pairs within a video and of every keyframe / background image across videos -> mapping
(incremental or global), keep the largest model -> a static video's frames take its background image's pose, a
moving video's other frames are posed by PnP against the model -> static videos the background left out are
posed from the moving subject's 2D tracks (`sfm.register_subject`, anchored on the videos the background posed)
-> cameras.json, background.ply, register_report.json (which path posed each video, and why).
pycolmap stages run in child processes (`sfm.isolated`) so that a fatal COLMAP error is a clear message.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
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
from sfm.export import colmap_params, write_ply
from sfm.frames import JPEG_QUALITY, Resize, image_name, select_frames, write_frames
from sfm.intrinsics import known_intrinsics
from sfm.isolated import run_isolated
from sfm.keyframes import KeyframeChoice, KeyframeReason, choose_keyframes, even_choice
from sfm.localize_frames import localize_all
from sfm.masks import mask_from_points, track_points, user_mask, write_mask
from sfm.options import ALL_CORES, CameraMotion, KeyframeSelection, Localize, Mapper, RegisterOptions, SubjectPath
from sfm.pairs import build_pairs, word_vectors
from sfm.plan import FramePose, VideoPlan
from sfm.register_subject import pose_from_subject
from sfm.report import write_report
from sfm.resume import StepLog, files_key, input_key
from sfm.static import SAMPLES, background_image, measure_motion, sample_frames
from sfm.video import ProbedVideo, probe_video, video_name
from tracking.tracks import Tracks, read_tracks

log = logging.getLogger(__name__)

MIN_KEYPOINTS = 50  # fewer SIFT features in an image: warn that it is untextured or blurred
MIN_SETTLED = 5  # settled samples a static background image needs; fewer: the median of all samples
Intrinsics = dict[str, tuple[np.ndarray, np.ndarray | None]]  # video name -> (K, dist), OpenCV, original pixels
Results = dict[str, dict[int, FramePose]]  # video name -> frame -> its outcome


class RegistrationError(DynreconError):
    """SfM could not put at least two videos into one model."""


@dataclass(kw_only=True)
class _Workspace:
    """The folders of one registration, its options, and what it records for the report on the way."""

    out: Path
    options: RegisterOptions
    timings: dict[str, float] = field(default_factory=dict)  # step -> seconds
    warnings: list[str] = field(default_factory=list)
    steps: StepLog | None = None  # the finished steps of earlier runs (resuming)
    unreadable: dict[str, str] = field(default_factory=dict)  # video file -> why it was left out

    @property
    def log(self) -> StepLog:
        if self.steps is None:
            self.steps = StepLog(self.sfm_dir)
        return self.steps

    @property
    def frames_dir(self) -> Path:
        return self.out / "frames"

    @property
    def sfm_dir(self) -> Path:
        return self.out / "sfm"

    @property
    def colmap_log(self) -> Path:
        return self.sfm_dir / "colmap.log"

    @property
    def database(self) -> Path:
        return self.sfm_dir / "database.db"

    @property
    def mask_dir(self) -> Path:
        return self.sfm_dir / "masks"

    @property
    def model_dir(self) -> Path:
        return self.sfm_dir / "models"

    @contextmanager
    def timed(self, step: str) -> Iterator[None]:
        """Adds the block's seconds to `step` (a step may be timed in parts)."""
        started = time.perf_counter()
        yield
        self.timings[step] = self.timings.get(step, 0.0) + time.perf_counter() - started


@dataclass(kw_only=True)
class _Sfm:
    """What the background SfM produced: the image pairs, the matching summary and the kept model."""

    pairs: list[tuple[str, str]] = field(default_factory=list)
    matching: dict[str, int] = field(default_factory=dict)
    rec: pycolmap.Reconstruction | None = None


def run(videos: Sequence[str | Path], out_dir: str | Path, options: RegisterOptions | None = None) -> Path:
    """Register `videos` into one world frame; returns the path of the written `cameras.json`."""
    options = options or RegisterOptions()
    paths = [Path(v) for v in videos]
    _check_videos(paths)
    ws = _Workspace(out=Path(out_dir), options=options)

    class _WarningCollector(logging.Handler):
        """Warnings (variable frame rate, unmasked videos, ...) also go into the report."""

        def emit(self, record: logging.LogRecord) -> None:
            ws.warnings.append(record.getMessage())

    collector = _WarningCollector(level=logging.WARNING)
    for name in ("sfm.video", "sfm.masks", __name__):
        logging.getLogger(name).addHandler(collector)
    try:
        with ws.timed("probe"):
            infos = _probe_all(paths, ws)
        ws.out.mkdir(parents=True, exist_ok=True)
        for stale in ("cameras.json", "background.ply", "register_report.json"):
            (ws.out / stale).unlink(missing_ok=True)  # never leave a previous run's result beside this report
        _clear_per_run(ws)
        return _register(infos, ws)
    finally:
        for name in ("sfm.video", "sfm.masks", __name__):
            logging.getLogger(name).removeHandler(collector)


def _probe_all(paths: list[Path], ws: _Workspace) -> list[ProbedVideo]:
    """Probe every video. One that cannot be read is left out with its one-line reason (a warning and the report),
    and the others go on; with fewer than two readable videos, the first reason is the error."""
    infos, errors = [], []
    for path in tqdm(paths, desc="probing videos", unit="video", leave=False):
        try:
            infos.append(probe_video(path))
        except InputError as error:
            errors.append(error)
            ws.unreadable[str(path)] = str(error)
            log.warning("left out: %s", error)
    if len(infos) < 2 and errors:
        raise errors[0]
    return infos


def _clear_per_run(ws: _Workspace) -> None:
    """Remove what every run writes anew (masks, the localization database); keep what a later run may reuse
    (the feature database and the models, checked against steps.json)."""
    ws.sfm_dir.mkdir(parents=True, exist_ok=True)
    if ws.mask_dir.exists():
        shutil.rmtree(ws.mask_dir)  # a stale mask would silently hide features of this run's frames
    (ws.sfm_dir / "localize.db").unlink(missing_ok=True)


def _register(infos: list[ProbedVideo], ws: _Workspace) -> Path:
    """The steps after probing, in order; each step's seconds go into the report."""
    options = ws.options
    with ws.timed("motion_test"):
        tracks = _tracks(options, ws.out)
        intrinsics = known_intrinsics(options.intrinsics, infos) if options.intrinsics else {}
    videos = _plan_videos(infos, tracks, ws)
    with ws.timed("decode"):
        names_of, masked = _write_images(videos, tracks, ws)
    mask_dir = ws.mask_dir if masked else None
    with ws.timed("extract"):
        keypoints = _extract(videos, names_of, intrinsics, mask_dir, ws)
    for name, count in keypoints.items():
        if count < MIN_KEYPOINTS:
            ws.warnings.append(f"{name}: only {count} SIFT features (untextured or blurred frame?)")
    sfm = _Sfm()
    with ws.timed("match"):
        sfm.pairs, sfm.matching = _match(names_of, ws)
    with ws.timed("map"):
        models = _map(videos, names_of, intrinsics, ws)
    sfm.rec = _largest_model(models, ws)
    with ws.timed("localize"):
        results = _localize(videos, sfm.rec, mask_dir, ws)
    with ws.timed("subject"):
        subject_report = pose_from_subject(videos, results, tracks, intrinsics, options, ws.warnings)

    registered_videos = [v for v in videos if any(r.pose is not None for r in results[v.info.name].values())]
    if len(registered_videos) < 2:
        names = ", ".join(v.info.name for v in registered_videos) or "none"
        _fail(
            ws,
            videos,
            results,
            sfm,
            subject_report,
            f"only {len(registered_videos)} of {len(videos)} videos registered ({names})",
        )
    with ws.timed("export"):
        path = _export(registered_videos, results, sfm.rec, subject_report, ws)
    _write_report(ws, videos, results, sfm, subject_report, error=None)
    return path


def _check_videos(videos: list[Path]) -> None:
    if len(videos) < 2:
        raise InputError(
            videos[0] if videos else None,
            "register needs at least two videos",
            fix="give every video of the scene",
        )
    names = [video_name(v) for v in videos]  # a name that cannot be a folder is the user's to fix, not left out
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


def _plan_videos(infos: list[ProbedVideo], tracks: Tracks | None, ws: _Workspace) -> list[VideoPlan]:
    """Which frames each video sends to SfM and which need a pose; static or moving camera, measured."""
    options = ws.options
    videos = []
    for info in tqdm(infos, desc="testing camera motion", unit="video", leave=False):
        motion = None
        with ws.timed("motion_test"):
            if options.camera_motion is CameraMotion.AUTO:
                motion = measure_motion(info)
                static = motion.static
                log.info("%s: %s", info.name, motion.reason)
                if motion.moved:
                    log.warning(motion.moved)
            else:
                static = options.camera_motion is CameraMotion.STATIC
        resize = Resize.for_video(info, options.long_side)
        with ws.timed("keyframes"):
            choice = None if static else _keyframes(info, ws, tracks)
        sfm_frames = np.zeros(0, np.int64) if choice is None else choice.frames
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
                keyframes=choice,
            )
        )
    return videos


def _keyframes(info: ProbedVideo, ws: _Workspace, tracks: Tracks | None) -> KeyframeChoice:
    """A moving video's SfM frames: by content (reused from an earlier run of the same video, settings and subject
    tracks) or evenly; the tracked subject is masked out of the measured motion."""
    options = ws.options
    if options.keyframes_by is KeyframeSelection.EVEN or options.step or options.time_step:  # a step asks for even
        frames = select_frames(info, step=options.step, time_step=options.time_step, max_frames=options.max_frames)
        return even_choice(frames)
    stat = info.path.stat()
    settings = (options.keyframe_motion, options.keyframe_survival, options.max_frames, options.mask_radius)
    points = track_points(tracks, info.name) if tracks is not None else {}
    subject = input_key(*((frame, xy.round(2).tolist()) for frame, xy in sorted(points.items())))
    key = input_key(str(info.path.resolve()), stat.st_size, stat.st_mtime_ns, info.num_frames, settings, subject)
    step = f"keyframes {info.name}"
    done = ws.log.result(step, key)
    if done is not None:
        return ws.log.reuse(step, _choice_from_json(done))
    resize = Resize.for_video(info, options.long_side)

    def masks(frame: int) -> np.ndarray | None:
        where = points.get(frame)
        return mask_from_points(where, resize, options.mask_radius) if where is not None else None

    choice = choose_keyframes(
        info,
        motion=options.keyframe_motion,
        survival=options.keyframe_survival,
        max_frames=options.max_frames,
        masks=masks if points and options.use_masks else None,
    )
    ws.log.record(step, key, {**choice.to_json(), "reasons": [r.value for r in choice.reasons]})
    log.info("%s: %d keyframes by content (%s)", info.name, len(choice.frames), choice.to_json()["by_reason"])
    return choice


def _choice_from_json(done: dict[str, Any]) -> KeyframeChoice:
    """A recorded keyframe choice (`_keyframes`' record) back as a KeyframeChoice."""
    return KeyframeChoice(
        method=done["method"],
        frames=np.asarray(done["frames"], dtype=np.int64),
        reasons=[KeyframeReason(r) for r in done["reasons"]],
        candidates=int(done["chosen_by_content"]),
        thinned=bool(done["thinned_to_max_frames"]),
        settings={"motion": done["motion"], "survival": done["survival"]},
    )


def _wanted_frames(info: ProbedVideo, sfm_frames: np.ndarray, tracks: Tracks | None, mode: Localize) -> np.ndarray:
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


def _write_images(videos: list[VideoPlan], tracks: Tracks | None, ws: _Workspace) -> tuple[dict[str, list[str]], int]:
    """The SfM images (sampled frames, or a static video's background image) and their masks.

    Returns video name -> its SfM image names, and how many masks were written."""
    options = ws.options
    names_of = {}
    masked = _write_masks([v for v in videos if not v.static], tracks, options, ws.mask_dir) if options.use_masks else 0
    for video in videos:
        names_of[video.info.name] = write_frames(video.info, video.sfm_frames, ws.frames_dir, video.resize)
        if video.static:
            masked += _write_background(video, ws.frames_dir, tracks, options, ws.mask_dir)
            names_of[video.info.name] = [video.background_name]
    return names_of, masked


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


def _write_background(
    video: VideoPlan, frames_dir: Path, tracks: Tracks | None, options: RegisterOptions, mask_dir: Path
) -> bool:
    """A static video's background image (and its mask where the subject stays); returns whether a mask was
    written."""
    frames = sample_frames(video.info, SAMPLES)
    if video.motion is not None and len(video.motion.settled) >= MIN_SETTLED:
        frames = np.array(video.motion.settled, dtype=np.int64)
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


def _extract(
    videos: list[VideoPlan],
    names_of: dict[str, list[str]],
    intrinsics: Intrinsics,
    mask_dir: Path | None,
    ws: _Workspace,
) -> dict[str, int]:
    """SIFT features of every SfM image into the database (kept from an earlier run when its images, masks and
    settings are the same); returns image name -> keypoint count."""
    args = _extract_args(videos, names_of, intrinsics, ws.options)
    images = [ws.frames_dir / name for names in names_of.values() for name in names]
    masks = sorted(mask_dir.rglob("*.png")) if mask_dir is not None else []
    key = input_key(args, ws.options.max_features, files_key(images), files_key(masks))
    done = ws.log.result("extract", key)
    if done is not None and ws.database.exists():
        return ws.log.reuse("extract", {str(k): int(v) for k, v in done.items()})
    ws.log.forget("extract", "match", "map")
    ws.database.unlink(missing_ok=True)
    keypoints: dict[str, int] = run_isolated(
        "feature extraction",
        colmap_steps.extract,
        {
            "database": str(ws.database),
            "image_dir": str(ws.frames_dir),
            "videos": args,
            "mask_dir": str(mask_dir) if mask_dir is not None else None,
            "max_features": ws.options.max_features,
            "num_threads": ws.options.num_threads,
        },
        ws.colmap_log,
    )
    ws.log.record("extract", key, keypoints)
    return keypoints


def _extract_args(
    videos: list[VideoPlan], names_of: dict[str, list[str]], intrinsics: Intrinsics, options: RegisterOptions
) -> list[dict[str, Any]]:
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


def _match(names_of: dict[str, list[str]], ws: _Workspace) -> tuple[list[tuple[str, str]], dict[str, int]]:
    """Sequential pairs within a video, keyframe and retrieved pairs across videos, matched (kept from an earlier
    run with the same features and pairs); returns the pairs and the matching summary."""
    options = ws.options
    words = word_vectors(_descriptors(ws.database)) if options.cross_partners > 0 and len(names_of) > 1 else {}
    pairs = build_pairs(
        names_of,
        overlap=options.sequential_overlap,
        keyframes=options.keyframes,
        partners=options.cross_partners,
        words=words,
    )
    key = input_key(ws.log.steps.get("extract", {}).get("key"), pairs, options.max_ratio)
    done = ws.log.result("match", key)
    if done is not None:
        return pairs, ws.log.reuse("match", {str(k): int(v) for k, v in done.items()})
    ws.log.forget("match", "map")
    with pycolmap.Database.open(str(ws.database)) as db:
        db.clear_matches()  # an interrupted run's partial matches
        db.clear_two_view_geometries()
    matching: dict[str, int] = run_isolated(
        "matching",
        colmap_steps.match,
        {
            "database": str(ws.database),
            "pairs": pairs,
            "max_ratio": ws.options.max_ratio,
            "num_threads": ws.options.num_threads,
        },
        ws.colmap_log,
    )
    ws.log.record("match", key, matching)
    return pairs, matching


def _descriptors(database: Path) -> dict[str, np.ndarray]:
    """image name -> its SIFT descriptors (N, 128) uint8, from the feature database."""
    with pycolmap.Database.open(str(database)) as db:
        return {image.name: np.asarray(db.read_descriptors(image.image_id).data) for image in db.read_all_images()}


def _map(
    videos: list[VideoPlan], names_of: dict[str, list[str]], intrinsics: Intrinsics, ws: _Workspace
) -> dict[str, int]:
    """The mapper's models in sfm/models/<name> (kept from an earlier run with the same matches and settings);
    returns model name -> registered images."""
    options = ws.options
    step = colmap_steps.map_global if options.mapper is Mapper.GLOBAL else colmap_steps.map_incremental
    fix_intrinsics = bool(intrinsics) and len(intrinsics) == len(videos)
    if intrinsics and not fix_intrinsics:
        ws.warnings.append("known intrinsics for only some videos: all intrinsics are refined")
    key = input_key(ws.log.steps.get("match", {}).get("key"), options.mapper, fix_intrinsics, options.init_min_inliers)
    done = ws.log.result("map", key)
    if done is not None and all((ws.model_dir / name).is_dir() for name in done):
        return ws.log.reuse("map", {str(k): int(v) for k, v in done.items()})
    ws.log.forget("map")
    if ws.model_dir.exists():
        shutil.rmtree(ws.model_dir)
    ws.model_dir.mkdir()
    models: dict[str, int] = run_isolated(
        f"mapping ({options.mapper.value})",
        step,
        {
            "database": str(ws.database),
            "image_dir": str(ws.frames_dir),
            "out_dir": str(ws.model_dir),
            "fix_intrinsics": fix_intrinsics,
            "init_min_inliers": options.init_min_inliers,
            "num_threads": options.num_threads,
            "num_images": sum(len(n) for n in names_of.values()),
        },
        ws.colmap_log,
    )
    ws.log.record("map", key, models)
    return models


def _largest_model(models: dict[str, int], ws: _Workspace) -> pycolmap.Reconstruction | None:
    """The model with the most images (None without a model); the others are named in a warning."""
    if not models:
        ws.warnings.append("background SfM found no model: no two images could be matched and triangulated")
        return None
    best = max(models, key=lambda k: models[k])
    rec = pycolmap.Reconstruction(str(ws.model_dir / best))
    if len(models) > 1:
        ws.warnings.append(
            f"{len(models)} models; kept model {best} with {models[best]} images "
            f"(others: {', '.join(f'{k}: {v}' for k, v in models.items() if k != best)})"
        )
    return rec


def _localize(
    videos: list[VideoPlan], rec: pycolmap.Reconstruction | None, mask_dir: Path | None, ws: _Workspace
) -> Results:
    """Every wanted frame's outcome: the model's pose, PnP against it, or the reason there is none."""
    if rec is None:
        return {
            v.info.name: {int(f): FramePose(pose=None, reason="background SfM found no model") for f in v.wanted}
            for v in videos
        }
    return localize_all(
        videos,
        rec,
        ws.database,
        ws.frames_dir,
        ws.sfm_dir,
        mask_dir,
        ws.colmap_log,
        max_features=ws.options.max_features,
        max_ratio=ws.options.max_ratio,
        min_inliers=ws.options.min_inliers,
        num_threads=ws.options.num_threads,
        inbetween=ws.options.inbetween,
    )


def _export(
    registered_videos: list[VideoPlan],
    results: Results,
    rec: pycolmap.Reconstruction | None,
    subject_report: dict[str, Any] | None,
    ws: _Workspace,
) -> Path:
    """background.ply (the model's points) and cameras.json (every posed frame); returns the cameras.json path."""
    cameras = CameraSet()
    clock_offsets = {c["name"]: c["offset_s"] for c in (subject_report or {}).get("cameras", [])}
    for video in registered_videos:
        cameras.videos.append(_video_cameras(video, results[video.info.name], clock_offsets.get(video.info.name)))
    if rec is not None:
        xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
        rgb = np.array([p.color for p in rec.points3D.values()], dtype=np.uint8).reshape(-1, 3)
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    write_ply(ws.out / "background.ply", xyz, rgb)
    return write_cameras(ws.out / "cameras.json", cameras)


def _video_cameras(video: VideoPlan, results: dict[int, FramePose], clock_offset: float | None) -> VideoCameras:
    """One video's posed frames in the cameras.json contract."""
    frames = []
    for frame, result in sorted(results.items()):
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
    return VideoCameras(
        name=video.info.name,
        width=video.info.width,
        height=video.info.height,
        fps=video.info.fps,
        frames=frames,
        clock_offset=clock_offset,
    )


def _write_report(
    ws: _Workspace,
    videos: list[VideoPlan],
    results: Results,
    sfm: _Sfm,
    subject: dict[str, Any] | None,
    *,
    error: str | None,
) -> None:
    write_report(
        ws.out / "register_report.json",
        videos=videos,
        results=results,
        timings=ws.timings,
        warnings=ws.warnings,
        options=ws.options,
        reused=ws.log.reused,
        unreadable=ws.unreadable,
        pairs=len(sfm.pairs),
        matching=sfm.matching,
        rec=sfm.rec,
        subject=subject,
        error=error,
    )


def _fail(
    ws: _Workspace,
    videos: list[VideoPlan],
    results: Results,
    sfm: _Sfm,
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
    message = f"{what}; cameras.json not written: {hint}. Details: {ws.out / 'register_report.json'}"
    _write_report(ws, videos, results, sfm, subject, error=message)
    raise RegistrationError(message)


__all__ = [
    "ALL_CORES",
    "CameraMotion",
    "Localize",
    "Mapper",
    "RegisterOptions",
    "RegistrationError",
    "SubjectPath",
    "read_cameras",
    "run",
]
