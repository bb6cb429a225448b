"""`dynrecon.truth`: the similarity from registered to true cameras."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dynrecon.truth import Similarity, similarity_to_truth, truth_of_frames
from reconstruct.outputs.points import FramePoints, read_points
from sfm.cameras import read_cameras

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "video_sample"


def test_similarity_to_truth_recovers_a_known_similarity():
    """Cameras of a world moved by a known similarity (as SfM's arbitrary frame is) align back exactly."""
    truth = read_cameras(SAMPLE / "truth_cameras.json")
    rotation = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    # X_sfm = (R^T (X_true - t)) / s, i.e. truth = s R X_sfm + t
    known = Similarity(scale=250.0, rotation=rotation, translation=np.array([900.0, -40.0, 1300.0]))
    inverse = Similarity(
        scale=1 / known.scale, rotation=rotation.T, translation=-(rotation.T @ known.translation) / known.scale
    )
    moved = read_cameras(SAMPLE / "truth_cameras.json")
    for video in moved.videos:
        video.frames = [inverse.camera(f) for f in video.frames]
    found = similarity_to_truth(moved, truth)
    assert found.scale == pytest.approx(known.scale, rel=1e-9)
    assert np.allclose(found.rotation, rotation, atol=1e-9)
    assert np.allclose(found.translation, known.translation, atol=1e-6)
    back = found.camera(moved.videos[1].frames[5])
    assert np.allclose(back.center, truth.videos[1].frames[5].center, atol=1e-6)
    assert np.allclose(back.R, truth.videos[1].frames[5].R, atol=1e-9)
    # A point seen by the moved cameras lands on the true point.
    xyz = np.array([[4000.0, 3800.0, 900.0]])
    assert np.allclose(found.apply(inverse.apply(xyz)), xyz, atol=1e-6)


def _rows(points: FramePoints, keep: list[int]) -> FramePoints:
    """`points` with only the rows `keep`: an estimate that lacks the others."""
    return replace(
        points,
        videos=[points.videos[i] for i in keep],
        frames=points.frames[keep],
        xyz=points.xyz[keep],
        observed=points.observed[keep],
    )


def test_only_the_truth_of_frames_the_estimate_has_is_scored() -> None:
    truth = read_points(SAMPLE / "truth.csv")
    assert truth_of_frames(truth, truth).num_frames == truth.num_frames
    keep = [i for i in range(truth.num_frames) if i not in (0, 3)]  # frames the registration lost
    estimate = _rows(truth, keep)
    subset = truth_of_frames(truth, estimate)
    assert subset.num_frames == len(keep) and subset.videos == estimate.videos
    np.testing.assert_array_equal(subset.xyz, truth.xyz[keep])


def test_a_video_the_solve_left_out_is_scored_as_unreconstructed() -> None:
    """Its frames have cameras but no rows (the solve found no clock for it): kept for the score, as `evaluate`
    counts them, not dropped as frames the registration lost."""
    truth = read_points(SAMPLE / "truth.csv")
    first = truth.videos[0]
    keep = [i for i, v in enumerate(truth.videos) if v != first]
    estimate = _rows(truth, keep)
    left_out = frozenset((v, int(f)) for v, f in zip(truth.videos, truth.frames, strict=True) if v == first)
    subset = truth_of_frames(truth, estimate, left_out)
    assert subset.num_frames == truth.num_frames
    assert truth_of_frames(truth, estimate).num_frames == len(keep)
