"""Poses for every wanted frame of every video: from the SfM model, or by PnP against it (`sfm.localize`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from sfm import colmap_steps
from sfm.export import image_reprojection_errors, opencv_intrinsics
from sfm.frames import image_name, write_frames
from sfm.isolated import run_isolated
from sfm.localize import Reference, localize, read_features, reference
from sfm.plan import FramePose, VideoPlan

NEAREST_REFERENCES = 2  # registered frames of the same video whose 3D points a query frame is matched to


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
) -> dict[str, dict[int, FramePose]]:
    """video name -> frame -> FramePose for every wanted frame."""
    # Frames not sent to SfM need features: decode them and extract into a second database.
    extra_names = {}
    for video in videos:
        if video.static:
            continue  # every frame takes the background image's pose
        extra = np.setdiff1d(video.wanted, video.sfm_frames)
        if len(extra):
            extra_names[video.info.name] = write_frames(
                video.info, extra, frames_dir, video.resize, desc="decoding frames to localize"
            )
    query_db = sfm_dir / "localize.db"
    if extra_names:
        videos_args = [
            {"name": k, "images": v, "camera_model": "SIMPLE_PINHOLE", "camera_params": ""}
            for k, v in extra_names.items()
        ]
        run_isolated(
            "feature extraction (frames to localize)",
            colmap_steps.extract,
            {
                "database": str(query_db),
                "image_dir": str(frames_dir),
                "videos": videos_args,
                "mask_dir": str(mask_dir) if mask_dir else None,
                "max_features": max_features,
                "num_threads": num_threads,
            },
            colmap_log,
        )
    results: dict[str, dict[int, FramePose]] = {}
    with pycolmap.Database.open(str(database)) as db:
        query = pycolmap.Database.open(str(query_db)) if extra_names else None
        try:
            for video in tqdm(videos, desc="localizing", unit="video", leave=False):
                if video.static:
                    results[video.info.name] = _static_video(video, rec)
                else:
                    results[video.info.name] = _localize_video(video, rec, db, query, max_ratio, min_inliers)
        finally:
            if query is not None:
                query.close()
    return results


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
    rec: pycolmap.Reconstruction,
    db: pycolmap.Database,
    query: pycolmap.Database | None,
    max_ratio: float,
    min_inliers: int,
) -> dict[int, FramePose]:
    name = video.info.name
    registered: dict[int, pycolmap.Image] = {}
    for frame in video.sfm_frames:
        image = rec.find_image_with_name(image_name(name, int(frame)))
        if image is not None and image.has_pose:
            registered[int(frame)] = image
    if not registered:
        return {int(f): FramePose(pose=None, reason="video not in the kept model") for f in video.wanted}
    db_ids = {image.name: image.image_id for image in db.read_all_images()}
    query_ids = {image.name: image.image_id for image in query.read_all_images()} if query is not None else {}
    camera = rec.cameras[next(iter(registered.values())).camera_id]
    intrinsics = opencv_intrinsics(camera, video.resize)
    results: dict[int, FramePose] = {}
    for frame, image in registered.items():
        errors = image_reprojection_errors(rec, image)
        results[frame] = FramePose(
            pose=image.cam_from_world(),
            source="sfm",
            intrinsics=intrinsics,
            error=float(errors.mean()) / video.resize.scale if len(errors) else None,
        )
    registered_frames = np.array(sorted(registered))
    references: dict[int, Reference] = {}
    todo = [int(f) for f in video.wanted if int(f) not in registered]
    for frame in tqdm(todo, desc=f"localizing {name}", unit="frame", leave=False):
        image_key = image_name(name, frame)
        if query is not None and image_key in query_ids:
            features = read_features(query, query_ids[image_key])
        elif image_key in db_ids:  # an SfM frame the mapper dropped
            features = read_features(db, db_ids[image_key])
        else:
            results[frame] = FramePose(pose=None, reason="no features")
            continue
        order = np.argsort(np.abs(registered_frames - frame), kind="stable")[:NEAREST_REFERENCES]
        refs = []
        for ref_frame in (int(f) for f in registered_frames[order]):
            if ref_frame not in references:
                ref_features = read_features(db, db_ids[image_name(name, ref_frame)])
                references[ref_frame] = reference(rec, registered[ref_frame], ref_features)
            refs.append(references[ref_frame])
        located = localize(features, refs, camera, max_ratio=max_ratio, min_inliers=min_inliers)
        dropped = frame in set(int(f) for f in video.sfm_frames)
        results[frame] = FramePose(
            pose=located.cam_from_world,
            reason=located.reason,
            source="pnp (dropped by SfM)" if dropped else "pnp",
            error=None if located.mean_error is None else located.mean_error / video.resize.scale,
            intrinsics=intrinsics,
            inliers=located.inliers,
        )
    return results
