"""Poses for frames outside the SfM model by SIFT: 2D-3D matches against nearby registered frames, then PnP.

A query frame's SIFT descriptors are matched (ratio test) to the descriptors of the nearest registered frames of
the same video that observe 3D points; `absolute_pose` (`pycolmap.estimate_and_refine_absolute_pose`: LO-RANSAC +
refinement, the video's camera fixed) gives the pose, as it does for the tracking path (`sfm.track_pose`). A frame
with too few inliers gets no pose and a reason in the report.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap


@dataclass(kw_only=True)
class Features:
    """Keypoints (N, 2) in COLMAP pixels of the SfM frame and their SIFT descriptors (N, 128) uint8."""

    xy: np.ndarray
    descriptors: np.ndarray


@dataclass(kw_only=True)
class Reference:
    """What a registered frame offers to localization: descriptors of keypoints with a 3D point, and those
    points."""

    descriptors: np.ndarray  # (M, 128) float32
    point_ids: np.ndarray  # (M,) int64
    xyz: np.ndarray  # (M, 3)


@dataclass(kw_only=True)
class Localized:
    cam_from_world: pycolmap.Rigid3d | None
    inliers: int
    matches: int
    mean_error: float | None  # mean inlier reprojection error, SfM pixels
    reason: str | None  # why there is no pose
    inlier_mask: np.ndarray | None = None  # (matches,) bool: the PnP inliers among the matches, with a pose


def read_features(db: pycolmap.Database, image_id: int) -> Features:
    keypoints = np.asarray(db.read_keypoints(image_id))
    descriptors = db.read_descriptors(image_id)
    data = np.asarray(getattr(descriptors, "data", descriptors))
    return Features(xy=keypoints[:, :2].astype(float), descriptors=data)


def reference(rec: pycolmap.Reconstruction, image: pycolmap.Image, features: Features) -> Reference:
    ids = np.array([p.point3D_id if p.has_point3D() else -1 for p in image.points2D], dtype=np.int64)
    keep = ids >= 0
    xyz = np.array([rec.points3D[i].xyz for i in ids[keep]]).reshape(-1, 3)
    return Reference(descriptors=features.descriptors[keep].astype(np.float32), point_ids=ids[keep], xyz=xyz)


def localize(
    query: Features,
    references: list[Reference],
    camera: pycolmap.Camera,
    *,
    max_ratio: float = 0.8,
    min_inliers: int = 30,
    max_error: float = 4.0,
) -> Localized:
    """PnP of one frame against the 3D points seen by `references`; None pose with a reason when it fails."""
    if len(query.xy) == 0:
        return Localized(cam_from_world=None, inliers=0, matches=0, mean_error=None, reason="no features")
    best: dict[int, tuple[float, int]] = {}  # point3D id -> (descriptor distance, query keypoint index)
    xyz_of: dict[int, np.ndarray] = {}
    # Approximate nearest neighbours (kd-trees): much faster than brute force, and the ratio test plus RANSAC absorb
    # the few wrong neighbours.
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    descriptors = query.descriptors.astype(np.float32)
    for ref in references:
        if len(ref.descriptors) < 2:
            continue
        for pair in matcher.knnMatch(descriptors, ref.descriptors, k=2):
            if len(pair) < 2 or pair[0].distance >= max_ratio * pair[1].distance:
                continue
            point_id = int(ref.point_ids[pair[0].trainIdx])
            if point_id not in best or pair[0].distance < best[point_id][0]:
                best[point_id] = (pair[0].distance, pair[0].queryIdx)
                xyz_of[point_id] = ref.xyz[pair[0].trainIdx]
    # One 3D point per query keypoint: keep the closest descriptor.
    by_keypoint: dict[int, tuple[float, int]] = {}
    for point_id, (distance, keypoint) in best.items():
        if keypoint not in by_keypoint or distance < by_keypoint[keypoint][0]:
            by_keypoint[keypoint] = (distance, point_id)
    keypoints = np.array(list(by_keypoint), dtype=np.int64)
    points2D = query.xy[keypoints].reshape(-1, 2)
    points3D = np.array([xyz_of[by_keypoint[k][1]] for k in keypoints]).reshape(-1, 3)
    return absolute_pose(points2D, points3D, camera, min_inliers=min_inliers, max_error=max_error)


def absolute_pose(
    points2D: np.ndarray,
    points3D: np.ndarray,
    camera: pycolmap.Camera,
    *,
    min_inliers: int = 30,
    max_error: float = 4.0,
) -> Localized:
    """LO-RANSAC PnP + refinement of 2D-3D matches (points2D (N, 2) in the camera's COLMAP pixels, points3D
    (N, 3)); a None pose with a reason when it fails. Shared by the SIFT and the tracking paths."""
    matches = len(points2D)
    if matches < min_inliers:
        return Localized(
            cam_from_world=None,
            inliers=0,
            matches=matches,
            mean_error=None,
            reason=f"only {matches} 2D-3D matches (< {min_inliers})",
        )
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = max_error
    estimation.ransac.random_seed = 0
    result = pycolmap.estimate_and_refine_absolute_pose(points2D, points3D, camera, estimation)
    if result is None:
        return Localized(
            cam_from_world=None,
            inliers=0,
            matches=matches,
            mean_error=None,
            reason=f"PnP failed on {matches} 2D-3D matches",
        )
    inliers = int(result["num_inliers"])
    if inliers < min_inliers:
        return Localized(
            cam_from_world=None,
            inliers=inliers,
            matches=matches,
            mean_error=None,
            reason=f"only {inliers} PnP inliers of {matches} matches (< {min_inliers})",
        )
    pose = result["cam_from_world"]
    mask = np.asarray(result["inlier_mask"], dtype=bool)
    in_cam = points3D[mask] @ pose.rotation.matrix().T + pose.translation
    errors = np.linalg.norm(camera.img_from_cam(in_cam) - points2D[mask], axis=1)
    return Localized(
        cam_from_world=pose,
        inliers=inliers,
        matches=matches,
        mean_error=float(errors.mean()),
        reason=None,
        inlier_mask=mask,
    )
