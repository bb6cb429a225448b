import cv2
import numpy as np
import pytest
from synthetic_motion import synthetic_problem, truth_array

from reconstruct.solver.rays import camera_normalization, normalized_image_points, viewing_rays


def test_rays_pass_through_the_true_points():
    problem, truth = synthetic_problem(frames=40, points=5)
    rays = viewing_rays(problem)
    X = truth_array(problem, truth)
    offset = X - problem.centers[:, None, :]
    along = np.sum(offset * rays, axis=-1)
    perpendicular = offset - along[..., None] * rays
    assert np.all(along > 0)  # in front of the camera
    assert np.abs(perpendicular).max() < 1e-6  # mm


def test_undistortion_inverts_opencv_projection():
    rng = np.random.default_rng(1)
    K = np.array([[800.0, 0, 320], [0, 790, 240], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.01])
    points = rng.uniform([-1, -1, 4], [1, 1, 6], size=(50, 3))
    uv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)
    xn = normalized_image_points(uv.reshape(-1, 2), K, dist)
    np.testing.assert_allclose(xn, points[:, :2] / points[:, 2:], atol=1e-7)


def test_normalization_makes_mean_camera_distance_one():
    rng = np.random.default_rng(2)
    centers = np.repeat(rng.normal(size=(4, 3)) * 1000, 10, axis=0) + rng.normal(size=(40, 3))
    video_index = np.repeat(np.arange(4), 10)
    norm = camera_normalization(centers, video_index)
    normalized = norm.apply(centers)
    video_centers = np.stack([normalized[video_index == v].mean(axis=0) for v in range(4)])
    gaps = [np.linalg.norm(video_centers[i] - video_centers[j]) for i in range(4) for j in range(i + 1, 4)]
    assert np.mean(gaps) == pytest.approx(1.0)
    np.testing.assert_allclose(norm.undo(normalized), centers)


def test_rays_of_distorted_frames_pass_through_the_true_points_and_unobserved_are_nan():
    problem, truth = synthetic_problem(frames=30, points=5)
    X = truth_array(problem, truth)
    dist = np.array([-0.15, 0.04, 0.001, -0.001, 0.0])
    for f in range(0, 30, 3):  # every third frame has lens distortion: its pixels are re-projected with it
        problem.dist[f] = dist
        rvec, _ = cv2.Rodrigues(problem.R[f])
        uv, _ = cv2.projectPoints(X[f], rvec, problem.t[f], problem.K[f], dist)
        problem.uv[f] = uv.reshape(-1, 2)
    problem.uv[4, 2] = np.nan
    rays = viewing_rays(problem)
    assert np.isnan(rays[4, 2]).all() and np.isfinite(np.delete(rays.reshape(-1, 3), 4 * 5 + 2, axis=0)).all()
    offset = X - problem.centers[:, None, :]
    perpendicular = offset - np.sum(offset * rays, axis=-1)[..., None] * rays
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1)[problem.observed], 1.0)
    assert np.nanmax(np.abs(perpendicular)) < 1e-3  # mm: undistortion is iterative
