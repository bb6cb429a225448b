"""`register`'s per-video steps as functions of files: each reads what the step before it wrote and writes its own
file, so that the serial stage (`sfm.stage.run`) and `dynrecon batch`'s per-video tasks run the same code.

    prepare_video   probed video -> plan (motion test, keyframes, wanted frames), SfM images and masks
                    -> sfm/videos/<video>/plan.json
    extract_videos  plan.json -> SIFT features in sfm/features/<video>.db -> sfm/videos/<video>/extract.json
    (the capture:   merge the per-video databases, match, map -> sfm/mapping.json; `sfm.stage.map_capture`)
    localize_video  plan.json, mapping.json, the kept model -> each wanted frame's pose
                    -> sfm/videos/<video>/poses.json
    (the capture:   subject path, cameras.json, background.ply, register_report.json; `sfm.stage.finish_capture`)

Each step's warnings and seconds go into its file and from there into register_report.json.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import InputError
from sfm import colmap_steps
from sfm.export import colmap_params
from sfm.frames import JPEG_QUALITY, Resize, image_name, select_frames, sfm_folder, write_frames
from sfm.intrinsics import known_intrinsics
from sfm.isolated import run_isolated
from sfm.keyframes import KeyframeChoice, choose_keyframes, even_choice
from sfm.layout import Layout
from sfm.localize_frames import localize_video as localize_frames
from sfm.masks import mask_from_points, track_points, user_mask, write_mask
from sfm.options import CameraMotion, KeyframeSelection, Localize, RegisterOptions
from sfm.plan import FramePose, VideoPlan
from sfm.plan_io import (
    PreparedVideo,
    StepNotes,
    choice_from_json,
    choice_to_json,
    read_prepared,
    write_poses,
    write_prepared,
)
from sfm.register_markers import markers_in_samples
from sfm.resume import StepLog, files_key, input_key
from sfm.static import SAMPLES, MotionTest, background_image, measure_motion, sample_frames
from sfm.video import ProbedVideo
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

# A video given by name with --fps (not here): the camera is taken as static, for the subject's tracks to pose
STAND_IN_MOTION = "not here (--fps): no pixels to test, taken as a static camera posed from the subject's tracks"
STAND_IN_UNPOSED = "not here (--fps): only the subject's tracks can pose it"

MIN_KEYPOINTS = 50  # fewer SIFT features in an image: warn that it is untextured or blurred
LISTED_IMAGES = 3  # images a few-features warning names before it only counts the rest
MIN_SETTLED = 5  # settled samples a static background image needs; fewer: the median of all samples
EXTRACT_STEP = "extract"
# The loggers whose warnings (variable frame rate, unmasked videos, a bumped camera, ...) go into the report.
REPORTED_LOGGERS = ("sfm.video", "sfm.masks", "sfm.stage", __name__)
NO_MODEL = "background SfM found no model"


@contextmanager
def collected(notes: StepNotes) -> Iterator[None]:
    """The block's warnings of REPORTED_LOGGERS into `notes.warnings`."""

    class _Collector(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            notes.warnings.append(record.getMessage())

    collector = _Collector(level=logging.WARNING)
    for name in REPORTED_LOGGERS:
        logging.getLogger(name).addHandler(collector)
    try:
        yield
    finally:
        for name in REPORTED_LOGGERS:
            logging.getLogger(name).removeHandler(collector)


@contextmanager
def timed(notes: StepNotes, step: str) -> Iterator[None]:
    """Adds the block's seconds to `step` (a step may be timed in parts)."""
    started = time.perf_counter()
    yield
    notes.timings[step] = notes.timings.get(step, 0.0) + time.perf_counter() - started


# cameras.json last: a parallel task that no longer finds it knows the others are already moved
OUTPUTS = ("background.ply", "register_report.json", "cameras.json")


def clear_outputs(out: Path) -> None:
    """Move a previous successful run's results into `Layout.previous_dir` (a failing run never leaves them beside
    its report, nor loses them; `finish_capture` removes them once the new ones are written); a failed run's report
    is removed. Safe to call from several of a capture's tasks at once."""
    out.mkdir(parents=True, exist_ok=True)
    previous = Layout(out).previous_dir
    if not (out / "cameras.json").is_file():
        (out / "register_report.json").unlink(missing_ok=True)  # a failed run's, or nothing
        return
    previous.mkdir(exist_ok=True)
    for name in OUTPUTS:
        with contextlib.suppress(FileNotFoundError):  # another task of the capture moved it first
            (out / name).replace(previous / name)


# ----------------------------------------------------------------------------------------------------------
# Plan and images


def prepare_video(info: ProbedVideo, out: Path, options: RegisterOptions, tracks: Tracks | None) -> PreparedVideo:
    """Plan one video (static or moving, its SfM frames, the frames that need a pose) and write its SfM images and
    masks; the outcome also goes to sfm/videos/<video>/plan.json."""
    layout = Layout(out)
    notes = StepNotes()
    steps = StepLog(layout.video_dir(info.name))
    with collected(notes):
        plan = plan_video(info, tracks, options, steps, notes)
        with timed(notes, "decode"):
            images, masks = write_video_images(plan, tracks, options, layout)
    notes.reused = steps.reused
    prepared = PreparedVideo(plan=plan, images=images, masks=masks, notes=notes)
    write_prepared(layout.plan(info.name), prepared)
    return prepared


def plan_video(
    info: ProbedVideo, tracks: Tracks | None, options: RegisterOptions, steps: StepLog, notes: StepNotes
) -> VideoPlan:
    """Which frames the video sends to SfM and which need a pose; static or moving camera, measured. The keyframe
    choice is kept in `steps` (the video's own step log) for a later run."""
    if info.stand_in:  # no pixels to test or to match: a static camera, for the subject's tracks to pose
        motion = MotionTest(static=True, reason=STAND_IN_MOTION)
        log.info("%s: %s", info.name, motion.reason)
        static = True
    else:
        motion, static = _motion(info, tracks, options, notes)
    resize = Resize.for_video(info, options.long_side)
    with timed(notes, "keyframes"):
        choice = None if static else _keyframes(info, options, steps, tracks)
    sfm_frames = np.zeros(0, np.int64) if choice is None else choice.frames
    wanted = wanted_frames(info, sfm_frames, tracks, options.localize)  # also checks the tracks' frames
    if static:  # a static video's pose costs nothing per frame: every frame gets it, whatever --localize says
        wanted = np.arange(info.num_frames, dtype=np.int64)
    return VideoPlan(
        info=info,
        resize=resize,
        sfm_frames=sfm_frames,
        wanted=wanted,
        motion=motion,
        motion_given=options.camera_motion is not CameraMotion.AUTO,
        static=static,
        keyframes=choice,
    )


def _motion(
    info: ProbedVideo, tracks: Tracks | None, options: RegisterOptions, notes: StepNotes
) -> tuple[MotionTest, bool]:
    """The motion test of one video, and whether it is taken as static (measured, or --camera-motion)."""
    with timed(notes, "motion_test"):
        # the tracked subject: where it hides the background, the samples say nothing about the camera
        subject = track_points(tracks, info.name) if tracks is not None else None
        # without tracks, markers in view are a subject to mask too (a board held up in front of a tripod)
        finder = markers_in_samples if options.find_markers else None
        motion = measure_motion(info, subject, options.mask_radius, finder)
        if options.camera_motion is CameraMotion.AUTO:
            static = motion.static
            log.info("%s: %s", info.name, motion.reason)
            if motion.moved:
                log.warning(motion.moved)
        else:
            static = options.camera_motion is CameraMotion.STATIC
            # the user's word is kept, but an assumption the data contradicts is said (a test that measured no
            # shift, an untextured or stand-in view, contradicts nothing)
            if motion.static != static and motion.shifts:
                log.warning(
                    "%s: --camera-motion %s given, but the motion test says %s; %s",
                    info.name,
                    options.camera_motion.value,
                    motion.reason,
                    "all its frames take one pose: if the camera moved, register again with --camera-motion auto"
                    if static
                    else "its frames go to SfM one by one (slower; pairs of one position have no baseline)",
                )
    return motion, static


def _keyframes(info: ProbedVideo, options: RegisterOptions, steps: StepLog, tracks: Tracks | None) -> KeyframeChoice:
    """A moving video's SfM frames: by content (reused from an earlier run of the same video, settings and subject
    tracks) or evenly; the tracked subject is masked out of the measured motion."""
    if options.keyframes_by is KeyframeSelection.EVEN or options.step or options.time_step:  # a step asks for even
        frames = select_frames(info, step=options.step, time_step=options.time_step, max_frames=options.max_frames)
        return even_choice(frames)
    stat = info.path.stat()
    settings = (options.keyframe_motion, options.keyframe_survival, options.max_frames, options.mask_radius)
    points = track_points(tracks, info.name) if tracks is not None else {}
    subject = input_key(*((frame, xy.round(2).tolist()) for frame, xy in sorted(points.items())))
    key = input_key(str(info.path.resolve()), stat.st_size, stat.st_mtime_ns, info.num_frames, settings, subject)
    step = f"keyframes {info.name}"
    done = steps.result(step, key)
    if done is not None:
        return steps.reuse(step, choice_from_json(done))
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
    steps.record(step, key, choice_to_json(choice))
    log.info("%s: %d keyframes by content (%s)", info.name, len(choice.frames), choice.to_json()["by_reason"])
    return choice


def wanted_frames(info: ProbedVideo, sfm_frames: np.ndarray, tracks: Tracks | None, mode: Localize) -> np.ndarray:
    """(W,) the frames of the video that should get a pose: the SfM frames and those `mode` asks for."""
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


def write_video_images(
    video: VideoPlan, tracks: Tracks | None, options: RegisterOptions, layout: Layout
) -> tuple[list[str], int]:
    """The video's SfM images (sampled frames, or a static video's background image) and their masks in
    masks/<video>/ (emptied first: a stale mask would hide features of this run's frames). Returns the SfM image
    names and how many masks were written."""
    video_masks = layout.mask_dir / sfm_folder(video.info.name)
    if video_masks.exists():
        shutil.rmtree(video_masks)
    if video.info.stand_in:
        return [], 0
    masked = 0
    if options.use_masks and not video.static:
        masked = _write_masks(video, tracks, options, layout.mask_dir)
    names = write_frames(video.info, video.sfm_frames, layout.frames_dir, video.resize)
    if video.static:
        masked += _write_background(video, layout.frames_dir, tracks, options, layout.mask_dir)
        names = [video.background_name]
    return names, masked


def _write_masks(video: VideoPlan, tracks: Tracks | None, options: RegisterOptions, mask_dir: Path) -> int:
    """Masks for every frame of the video that will have features extracted; returns how many were written."""
    written = 0
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


# ----------------------------------------------------------------------------------------------------------
# Feature extraction


@dataclass(kw_only=True)
class CaptureFacts:
    """What every video's extraction needs to know about the whole capture, read from the plan files."""

    wide_baseline: bool  # any static video: one descriptor kind (DSP-SIFT with affine shapes) for all images
    masked: bool  # any mask written: extraction reads masks/
    # `--intrinsics` per video name, matched against the whole capture (a file's cameras in order need all videos)
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]] = field(default_factory=dict)


def capture_facts(out: Path, videos: list[str], options: RegisterOptions | None = None) -> CaptureFacts:
    layout = Layout(out)
    prepared = [read_prepared(layout.plan(v)) for v in videos]
    given = options.intrinsics if options is not None else None
    intrinsics = known_intrinsics(given, [p.plan.info for p in prepared]) if given else {}
    return CaptureFacts(
        wide_baseline=any(p.plan.static and p.images for p in prepared),  # a name (--fps) sends no image
        masked=sum(p.masks for p in prepared) > 0,
        intrinsics=intrinsics,
    )


@dataclass(kw_only=True)
class Extraction:
    """One video's extraction: its colmap_steps.extract arguments and the key of its inputs; `keypoints` (image
    name -> count) once done."""

    video: str
    key: str
    kwargs: dict[str, Any] | None  # None: the video has no SfM image
    keypoints: dict[str, int] | None = None


def plan_extraction(out: Path, video: str, options: RegisterOptions, facts: CaptureFacts) -> Extraction:
    """The extraction of `video` into sfm/features/<video>.db, with `keypoints` filled when an earlier run's
    features are still those of the same images, masks and settings."""
    layout = Layout(out)
    prepared = read_prepared(layout.plan(video))
    plan = prepared.plan
    model, params = options.camera_model, ""
    if video in facts.intrinsics:
        K, dist = facts.intrinsics[video]
        model, values = colmap_params(K, dist, plan.resize)
        params = ",".join(repr(float(v)) for v in values)
    args = {
        "name": video,
        "images": prepared.images,
        "camera_model": model,
        "camera_params": params,
        "max_features": options.background_features if plan.static else options.max_features,
        "wide_baseline": facts.wide_baseline,
    }
    mask_dir = layout.mask_dir if facts.masked else None
    images = [layout.frames_dir / name for name in prepared.images]
    masks = sorted((mask_dir / sfm_folder(video)).rglob("*.png")) if mask_dir is not None else []
    key = input_key([args], options.max_features, files_key(images), files_key(masks))
    if not prepared.images:
        layout.features(video).unlink(missing_ok=True)  # an earlier run's features must not be merged
        return Extraction(video=video, key=key, kwargs=None, keypoints={})
    database = layout.features(video)
    steps = StepLog(layout.video_dir(video))
    done = steps.result(EXTRACT_STEP, key)
    kwargs = {
        "database": str(database),
        "image_dir": str(layout.frames_dir),
        "videos": [args],
        "mask_dir": str(mask_dir) if mask_dir is not None else None,
        "max_features": options.max_features,
        "num_threads": options.num_threads,
    }
    if done is not None and database.exists():
        return Extraction(video=video, key=key, kwargs=kwargs, keypoints={str(k): int(v) for k, v in done.items()})
    return Extraction(video=video, key=key, kwargs=kwargs)


def start_extraction(out: Path, extraction: Extraction) -> None:
    """Before extracting: no record of the step and no database of an earlier run."""
    layout = Layout(out)
    StepLog(layout.video_dir(extraction.video)).forget(EXTRACT_STEP)
    layout.features(extraction.video).unlink(missing_ok=True)
    layout.features(extraction.video).parent.mkdir(parents=True, exist_ok=True)


def finish_extraction(out: Path, extraction: Extraction, seconds: float, reused: bool) -> None:
    """Record the extraction (its step log, and sfm/videos/<video>/extract.json with its warnings and seconds)."""
    layout = Layout(out)
    keypoints = extraction.keypoints or {}
    notes = StepNotes(timings={"extract": seconds}, reused=[EXTRACT_STEP] if reused else [])
    warning = _few_features(extraction.video, keypoints)
    if warning is not None:
        notes.warnings.append(warning)
    if not reused and extraction.kwargs is not None:
        StepLog(layout.video_dir(extraction.video)).record(EXTRACT_STEP, extraction.key, keypoints)
    document = {"key": extraction.key, "keypoints": keypoints, "images": len(keypoints), **notes.to_json()}
    atomic_write_text(layout.extraction(extraction.video), json.dumps(document, indent=1) + "\n")


def _few_features(video: str, keypoints: dict[str, int]) -> str | None:
    """One line for a video whose SfM images have under MIN_KEYPOINTS SIFT features (every image: the whole view is
    dark, untextured, blurred or tiny; some: frames a hand or a blur covered), naming the first few."""
    few = {name: count for name, count in keypoints.items() if count < MIN_KEYPOINTS}
    if not few:
        return None
    low, high = min(few.values()), max(few.values())
    counts = f"{low}-{high}" if low < high else str(low)
    if len(few) == len(keypoints):
        which = "its SfM image has" if len(few) == 1 else f"every one of its {len(few)} SfM images has"
        return (
            f"{video}: {which} under {MIN_KEYPOINTS} SIFT features ({counts}): a dark, untextured, blurred or tiny "
            "view (a covered lens?) cannot be registered"
        )
    names = sorted(few)
    listed = ", ".join(names[:LISTED_IMAGES]) + (
        f" and {len(names) - LISTED_IMAGES} more" if len(names) > LISTED_IMAGES else ""
    )
    return (
        f"{video}: {len(few)} of its {len(keypoints)} SfM images have under {MIN_KEYPOINTS} SIFT features ({counts}; "
        f"untextured or blurred frames?): {listed}"
    )


def few_features_reason(out: Path, video: str) -> str | None:
    """The failure reason of a video none of whose SfM images had MIN_KEYPOINTS SIFT features (None otherwise, or
    before extraction)."""
    path = Layout(out).extraction(video)
    if not path.is_file():
        return None
    keypoints = json.loads(path.read_text(encoding="utf-8")).get("keypoints") or {}
    if not keypoints or max(keypoints.values()) >= MIN_KEYPOINTS:
        return None
    most = max(keypoints.values())
    return f"no SfM image of it has {MIN_KEYPOINTS} SIFT features (at most {most}): dark, untextured, blurred or tiny"


Runner = Callable[[str, Callable[..., Any], dict[str, Any], Path], Any]  # sfm.isolated.run_isolated's signature


def extract_videos(
    out: Path, videos: list[str], options: RegisterOptions, facts: CaptureFacts, runner: Runner = run_isolated
) -> None:
    """SIFT features of each of `videos` (all of a capture's, or one: a batch task) into its own database, kept
    from an earlier run when its images, masks and settings are the same; the extractions run one after the other
    in one child process (`runner`). `facts`: `capture_facts` of the whole capture."""
    started = time.perf_counter()
    extractions = [plan_extraction(out, video, options, facts) for video in videos]
    todo = [e for e in extractions if e.keypoints is None and e.kwargs is not None]
    for extraction in todo:
        start_extraction(out, extraction)
    if todo:
        log_path = Layout(out).colmap_log if len(videos) > 1 else Layout(out).video_log(videos[0])
        counts: list[dict[str, int]] = runner(
            "feature extraction", colmap_steps.extract_each, {"calls": [e.kwargs for e in todo]}, log_path
        )
        for extraction, keypoints in zip(todo, counts, strict=True):
            extraction.keypoints = keypoints
    seconds = (time.perf_counter() - started) / max(1, len(extractions))  # one child for all: seconds split evenly
    ran = {id(e) for e in todo}
    for extraction in extractions:
        finish_extraction(out, extraction, seconds, reused=id(extraction) not in ran and extraction.kwargs is not None)


def merge_features(out: Path, videos: list[str], target: Path) -> None:
    """The per-video feature databases of `videos` (in this order) merged into `target` (made anew)."""
    layout = Layout(out)
    sources = [layout.features(v) for v in videos if layout.features(v).exists()]
    target.unlink(missing_ok=True)
    if not sources:
        pycolmap.Database.open(str(target)).close()
        return
    if len(sources) == 1:
        shutil.copyfile(sources[0], target)
        return
    partial = target.with_name(f".{target.name}.merging")
    current = sources[0]
    for index, source in enumerate(sources[1:]):
        into = target if index == len(sources) - 2 else partial.with_suffix(f".{index}.db")
        into.unlink(missing_ok=True)
        with (
            pycolmap.Database.open(str(current)) as first,
            pycolmap.Database.open(str(source)) as second,
            pycolmap.Database.open(str(into)) as merged,
        ):
            pycolmap.Database.merge(first, second, merged)
        if current != sources[0]:
            current.unlink()
        current = into


# ----------------------------------------------------------------------------------------------------------
# In-between posing


def localize_video(out: Path, video: str, options: RegisterOptions) -> dict[int, FramePose]:
    """Every wanted frame's pose of one video, once the capture's mapping is done (sfm/mapping.json names the kept
    model): the model's, tracked from its keyframes, or SIFT-PnP against the model. Written to
    sfm/videos/<video>/poses.json with the step's warnings and seconds."""
    layout = Layout(out)
    notes = StepNotes()
    plan = read_prepared(layout.plan(video)).plan
    mapping = json.loads(layout.mapping.read_text(encoding="utf-8"))
    with collected(notes), timed(notes, "localize"):
        if plan.info.stand_in:
            poses = {int(f): FramePose(pose=None, reason=STAND_IN_UNPOSED) for f in plan.wanted}
        elif mapping["model"] is None:
            poses = {int(f): FramePose(pose=None, reason=NO_MODEL) for f in plan.wanted}
        else:
            rec = pycolmap.Reconstruction(str(layout.model_dir / mapping["model"]))
            poses = localize_frames(
                plan,
                rec,
                layout.database,
                layout.frames_dir,
                layout.localize_db(video),
                layout.mask_dir if mapping["masked"] else None,
                layout.video_log(video),
                max_features=options.max_features,
                max_ratio=options.max_ratio,
                min_inliers=options.min_inliers,
                num_threads=options.num_threads,
                inbetween=options.inbetween,
            )
    if poses and all(p.pose is None for p in poses.values()):
        why = few_features_reason(out, video)  # the model lacks the video because its images had nothing to match
        if why is not None:
            poses = {f: replace(p, reason=f"{p.reason}: {why}") for f, p in poses.items()}
    write_poses(layout.poses(video), video, poses, notes)
    return poses
