"""Scoring a reconstruction against a known truth (the video sample, simulations): the similarity that maps the
registered cameras onto the true ones, and the accuracy of the points moved by it.

SfM's world has its own origin, orientation and scale, so a result is compared only after that similarity.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from reconstruct.outputs.points import FramePoints, read_points
from sfm.cameras import CameraSet, FrameCamera, read_cameras
from simulation.evaluate import ReconstructionAccuracy, evaluate

log = logging.getLogger(__name__)

__all__ = ["Similarity", "align_to_truth", "score_points", "similarity_to_truth", "truth_of_frames"]


@dataclass(kw_only=True)
class Similarity:
    """X_true = scale * rotation @ X + translation."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        """xyz: (..., 3) -> (..., 3) in the target world."""
        return self.scale * xyz @ self.rotation.T + self.translation

    def camera(self, camera: FrameCamera) -> FrameCamera:
        """`camera` (cam_from_world of the source world) as a camera of the target world (translation in target
        units: the camera's own scale is the target's)."""
        R = camera.R @ self.rotation.T
        t = self.scale * camera.t - R @ self.translation
        return dataclasses.replace(camera, R=R, t=t)


def similarity_to_truth(cameras: CameraSet, truth_cameras: CameraSet) -> Similarity:
    """The similarity that best maps the registered cameras of the frames both sets have onto the true ones (SfM
    worlds have their own origin, rotation and scale).

    The rotation comes from the camera orientations (R_true^T R_est, averaged), scale and translation from the camera
    centres. Handheld cameras' centres lie close to a line, so a centres-only fit leaves the rotation about that line
    loose (a visible tilt on the video sample); orientations fix it.
    """
    true_frames = {(v.name, f.frame): f for v in truth_cameras.videos for f in v.frames}
    pairs = [
        (f, true_frames[(v.name, f.frame)])
        for v in cameras.videos
        for f in v.frames
        if (v.name, f.frame) in true_frames
    ]
    if len(pairs) < 3:
        raise InputError(
            None,
            f"only {len(pairs)} registered frames have a true camera; need 3 to align",
            fix="score against the truth of the same videos",
        )
    M = sum((true.R.T @ est.R for est, true in pairs), np.zeros((3, 3)))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    source = np.array([est.center for est, _ in pairs]) @ R.T
    target = np.array([true.center for _, true in pairs])
    a, b = source - source.mean(axis=0), target - target.mean(axis=0)
    s = float((a * b).sum() / (a * a).sum())
    t = target.mean(axis=0) - s * source.mean(axis=0)
    return Similarity(scale=s, rotation=R, translation=t)


def align_to_truth(points: FramePoints, cameras: CameraSet, truth_cameras: CameraSet) -> FramePoints:
    """`points` moved into the truth's world by `similarity_to_truth` of their cameras."""
    return dataclasses.replace(points, xyz=similarity_to_truth(cameras, truth_cameras).apply(points.xyz))


def truth_of_frames(
    truth: FramePoints, points: FramePoints, left_out: frozenset[tuple[str, int]] = frozenset()
) -> FramePoints:
    """The rows of `truth` whose (video, frame) `points` has: frames the registration lost are not scored; and those
    of `left_out`, posed (video, frame)s of videos the solve left out, which the score counts as unreconstructed."""
    index = points.index()
    keep = [
        i
        for i, (v, f) in enumerate(zip(truth.videos, truth.frames, strict=True))
        if (v, int(f)) in index or (v, int(f)) in left_out
    ]
    return FramePoints(
        videos=[truth.videos[i] for i in keep],
        frames=truth.frames[keep],
        point_names=truth.point_names,
        xyz=truth.xyz[keep],
        observed=truth.observed[keep],
    )


def score_points(
    points_path: Path, cameras_path: Path, truth_path: Path, truth_cameras_path: Path
) -> ReconstructionAccuracy:
    """Accuracy of `points_path` (points3d.csv) after alignment of its cameras (`cameras_path`, cameras.json) to the
    true ones, against `truth_path` (same layout as points3d.csv). Truth rows of frames the registration lost are
    left out (the log says how many)."""
    points = read_points(points_path)
    cameras = read_cameras(cameras_path)
    aligned = align_to_truth(points, cameras, read_cameras(truth_cameras_path))
    truth = read_points(truth_path)
    solved = set(points.videos)
    # posed, but left out of the solve (its clock not found: report.json temporal.left_out): unreconstructed
    left_out = frozenset(
        (video.name, frame.frame) for video in cameras.videos if video.name not in solved for frame in video.frames
    )
    subset = truth_of_frames(truth, points, left_out)
    if subset.num_frames < truth.num_frames:
        log.warning(
            "%d of %d truth frames have no registered camera; not scored",
            truth.num_frames - subset.num_frames,
            truth.num_frames,
        )
    return evaluate(aligned, subset, estimate_path=points_path, truth_path=truth_path)
