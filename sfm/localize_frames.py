"""Poses for every wanted frame of every video: from the SfM model, by tracking the keyframes' features
(`sfm.track_pose`), or by SIFT matching against the model (`sfm.localize`) where tracking fails or is off."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from sfm import colmap_steps
from sfm.export import image_reprojection_errors, opencv_intrinsics
from sfm.frames import image_name, write_frames
from sfm.isolated import run_isolated
from sfm.localize import Reference, localize, read_features, reference
from sfm.options import InBetween
from sfm.plan import FramePose, VideoPlan
from sfm.track_pose import Masks, Seed, seed_from_image, track_video

log = logging.getLogger(__name__)

NEAREST_REFERENCES = 2  # registered frames of the same video whose 3D points a query frame is matched to
ADDED_KEYFRAME = "tracked (added keyframe)"  # a tracked frame that later frames were tracked from (sfm.track_pose)


def localize_all(
    videos: list[VideoPlan],
    rec: pycolmap.Reconstruction,
    database: Path,
    frames_dir: Path,
    sfm_dir: Path,
    mask_dir: Path | None,
    colmap_log: Path,
    *,
    max_features: int,
    max_ratio: float,
    min_inliers: int,
    num_threads: int,
    inbetween: InBetween = InBetween.TRACK,
) -> dict[str, dict[int, FramePose]]:
    """video name -> frame -> FramePose for every wanted frame: `localize_video` for each video, its frames to
    localize by SIFT in `sfm_dir/localize_<video>.db`."""
    return {
        video.info.name: localize_video(
            video,
            rec,
            database,
            frames_dir,
            sfm_dir / f"localize_{video.info.name}.db",
            mask_dir,
            colmap_log,
            max_features=max_features,
            max_ratio=max_ratio,
            min_inliers=min_inliers,
            num_threads=num_threads,
            inbetween=inbetween,
        )
        for video in videos
    }


def localize_video(
    video: VideoPlan,
    rec: pycolmap.Reconstruction,
    database: Path,
    frames_dir: Path,
    query_db: Path,
    mask_dir: Path | None,
    colmap_log: Path,
    *,
    max_features: int,
    max_ratio: float,
    min_inliers: int,
    num_threads: int,
    inbetween: InBetween = InBetween.TRACK,
) -> dict[int, FramePose]:
    """frame -> FramePose for every wanted frame of one video: the model's pose, tracking from the keyframes, or
    SIFT-PnP against the model (features of the frames SfM did not see go into `query_db`, made anew)."""
    if video.static:
        return _static_video(video, rec)
    registered = _registered(video, rec)
    if not registered:
        return {int(f): FramePose(pose=None, reason="video not in the kept model") for f in video.wanted}
    results = _model_poses(video, rec, registered)
    todo = {int(f): "" for f in video.wanted if int(f) not in registered}
    if inbetween is InBetween.TRACK and todo:
        posed, todo = _track(video, rec, registered, sorted(todo), mask_dir, min_inliers)
        results.update(posed)
    query_db.unlink(missing_ok=True)  # an earlier run's features of other frames
    if todo:
        results.update(
            _sift(
                video,
                todo,
                rec,
                database,
                frames_dir,
                query_db,
                mask_dir,
                colmap_log,
                max_features=max_features,
                max_ratio=max_ratio,
                min_inliers=min_inliers,
                num_threads=num_threads,
            )
        )
    return results


def _registered(video: VideoPlan, rec: pycolmap.Reconstruction) -> dict[int, pycolmap.Image]:
    """The video's SfM frames that the kept model posed: frame -> image."""
    registered = {}
    for frame in video.sfm_frames:
        image = rec.find_image_with_name(image_name(video.info.name, int(frame)))
        if image is not None and image.has_pose:
            registered[int(frame)] = image
    return registered


def _model_poses(
    video: VideoPlan, rec: pycolmap.Reconstruction, registered: dict[int, pycolmap.Image]
) -> dict[int, FramePose]:
    camera = rec.cameras[next(iter(registered.values())).camera_id]
    intrinsics = opencv_intrinsics(camera, video.resize)
    results = {}
    for frame, image in registered.items():
        errors = image_reprojection_errors(rec, image)
        results[frame] = FramePose(
            pose=image.cam_from_world(),
            source="sfm",
            intrinsics=intrinsics,
            error=float(errors.mean()) / video.resize.scale if len(errors) else None,
            inliers=len(errors),
        )
    return results


def _mask_reader(mask_dir: Path | None, video: str) -> Masks:
    """frame -> the frame's feature mask (SfM pixels, 0 = subject) when `register` wrote one."""

    def read(frame: int) -> np.ndarray | None:
        if mask_dir is None:
            return None
        path = mask_dir / f"{image_name(video, frame)}.png"
        return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.exists() else None

    return read


def _track(
    video: VideoPlan,
    rec: pycolmap.Reconstruction,
    registered: dict[int, pycolmap.Image],
    todo: list[int],
    mask_dir: Path | None,
    min_inliers: int,
) -> tuple[dict[int, FramePose], dict[int, str]]:
    """Poses of the `todo` frames by tracking; returns them and the frames left for SIFT with the reason."""
    name = video.info.name
    camera = rec.cameras[next(iter(registered.values())).camera_id]
    intrinsics = opencv_intrinsics(camera, video.resize)
    seeds: dict[int, Seed] = {f: seed_from_image(rec, image, video.resize) for f, image in registered.items()}
    tracking = track_video(
        video.info.path,
        seeds,
        todo,
        camera,
        video.resize,
        _mask_reader(mask_dir, name),
        min_inliers=min_inliers,
        desc=f"tracking {name}",
    )
    posed = {
        frame: FramePose(
            pose=tracked.located.cam_from_world,
            source=ADDED_KEYFRAME if frame in tracking.added else "tracked",
            error=None if tracked.located.mean_error is None else tracked.located.mean_error / video.resize.scale,
            intrinsics=intrinsics,
            inliers=tracked.located.inliers,
        )
        for frame, tracked in tracking.posed.items()
    }
    if tracking.added:
        log.info("%s: %d frames promoted to keyframes of the tracking", name, len(tracking.added))
    if tracking.failed:
        log.info("%s: %d of %d frames not posed by tracking, trying SIFT", name, len(tracking.failed), len(todo))
    return posed, tracking.failed


def _sift(
    video: VideoPlan,
    todo: dict[int, str],
    rec: pycolmap.Reconstruction,
    database: Path,
    frames_dir: Path,
    query_db: Path,
    mask_dir: Path | None,
    colmap_log: Path,
    *,
    max_features: int,
    max_ratio: float,
    min_inliers: int,
    num_threads: int,
) -> dict[int, FramePose]:
    """SIFT-PnP of the `todo` frames (frame -> why tracking did not pose it) of one video."""
    # Frames not sent to SfM need features: decode them and extract into a database of their own.
    frames = np.setdiff1d(np.array(sorted(todo), dtype=np.int64), video.sfm_frames)
    extra: list[str] = []
    if len(frames):
        extra = write_frames(video.info, frames, frames_dir, video.resize, desc="decoding frames to localize")
        run_isolated(
            "feature extraction (frames to localize)",
            colmap_steps.extract,
            {
                "database": str(query_db),
                "image_dir": str(frames_dir),
                "videos": [
                    {"name": video.info.name, "images": extra, "camera_model": "SIMPLE_PINHOLE", "camera_params": ""}
                ],
                "mask_dir": str(mask_dir) if mask_dir else None,
                "max_features": max_features,
                "num_threads": num_threads,
            },
            colmap_log,
        )
    with pycolmap.Database.open(str(database)) as db:
        query = pycolmap.Database.open(str(query_db)) if extra else None
        try:
            return _localize_video(video, todo, rec, db, query, max_ratio, min_inliers)
        finally:
            if query is not None:
                query.close()


def _static_video(video: VideoPlan, rec: pycolmap.Reconstruction) -> dict[int, FramePose]:
    """Every wanted frame of a static video takes the pose of its background image, when the model has it."""
    image = rec.find_image_with_name(video.background_name)
    if image is None or not image.has_pose:
        return {int(f): FramePose(pose=None, reason="background image not in the kept model") for f in video.wanted}
    errors = image_reprojection_errors(rec, image)
    pose = FramePose(
        pose=image.cam_from_world(),
        source="static",
        intrinsics=opencv_intrinsics(rec.cameras[image.camera_id], video.resize),
        error=float(errors.mean()) / video.resize.scale if len(errors) else None,
        inliers=len(errors),
    )
    return {int(f): pose for f in video.wanted}


def _localize_video(
    video: VideoPlan,
    todo: dict[int, str],
    rec: pycolmap.Reconstruction,
    db: pycolmap.Database,
    query: pycolmap.Database | None,
    max_ratio: float,
    min_inliers: int,
) -> dict[int, FramePose]:
    """SIFT-PnP of the `todo` frames (frame -> why tracking did not pose them, "" when it was off)."""
    name = video.info.name
    registered = _registered(video, rec)
    db_ids = {image.name: image.image_id for image in db.read_all_images()}
    query_ids = {image.name: image.image_id for image in query.read_all_images()} if query is not None else {}
    camera = rec.cameras[next(iter(registered.values())).camera_id]
    intrinsics = opencv_intrinsics(camera, video.resize)
    results: dict[int, FramePose] = {}
    registered_frames = np.array(sorted(registered))
    references: dict[int, Reference] = {}
    sfm_frames = set(int(f) for f in video.sfm_frames)
    for frame, tracking in tqdm(sorted(todo.items()), desc=f"localizing {name} by SIFT", unit="frame", leave=False):
        image_key = image_name(name, frame)
        before = f"{tracking}; SIFT: " if tracking else ""
        if query is not None and image_key in query_ids:
            features = read_features(query, query_ids[image_key])
        elif image_key in db_ids:  # an SfM frame the mapper dropped
            features = read_features(db, db_ids[image_key])
        else:
            results[frame] = FramePose(pose=None, reason=f"{before}no features")
            continue
        order = np.argsort(np.abs(registered_frames - frame), kind="stable")[:NEAREST_REFERENCES]
        refs = []
        for ref_frame in (int(f) for f in registered_frames[order]):
            if ref_frame not in references:
                ref_features = read_features(db, db_ids[image_name(name, ref_frame)])
                references[ref_frame] = reference(rec, registered[ref_frame], ref_features)
            refs.append(references[ref_frame])
        located = localize(features, refs, camera, max_ratio=max_ratio, min_inliers=min_inliers)
        results[frame] = FramePose(
            pose=located.cam_from_world,
            reason=None if located.reason is None else f"{before}{located.reason}",
            source="pnp (dropped by SfM)" if frame in sfm_frames else "pnp",
            error=None if located.mean_error is None else located.mean_error / video.resize.scale,
            intrinsics=intrinsics,
            inliers=located.inliers,
        )
    return results
