"""Small captures with known trajectories for the refinement's tests (tests/reconstruct/test_refine.py,
test_clock_polish.py): points on Lissajous paths seen by 4 cameras around them, one camera per capture time."""

from __future__ import annotations

import numpy as np

from reconstruct.solver.problem import Problem
from simulation.simulate import look_at, project

DISTANCE_MM = 2700.0
K = np.array([[1000.0, 0, 499.5], [0, 1000.0, 499.5], [0, 0, 1.0]])


def trajectories(times: np.ndarray, points: int = 4) -> np.ndarray:
    """(F, P, 3) smooth motion in mm: each point on its own Lissajous path, ~0.5 m across, ~1 Hz."""
    phase = np.arange(points)[None, :]
    t = times[:, None]
    x = 300 * np.sin(2 * np.pi * 0.9 * t + phase)
    y = 200 * np.cos(2 * np.pi * 1.3 * t + 0.5 * phase)
    z = 1000 + 150 * np.sin(2 * np.pi * 0.7 * t + 0.3 * phase) + 100 * phase
    return np.stack([x, y, z], axis=-1)


def capture(
    times: np.ndarray, camera_of: np.ndarray, noise_px: float = 0.0, seed: int = 0, cameras: int = 4
) -> tuple[Problem, np.ndarray]:
    """A Problem seeing `trajectories(times)` with camera camera_of[f] at frame f; returns (problem, truth)."""
    truth = trajectories(times)
    F, P = truth.shape[:2]
    target = np.array([0.0, 0.0, 1000.0])
    up = np.array([0.0, 0.0, 1.0])
    poses = []
    for c in range(cameras):
        angle = 2 * np.pi * c / cameras + 0.3
        poses.append(look_at(target + DISTANCE_MM * np.array([np.cos(angle), np.sin(angle), 0.1]), target, up))
    R = np.stack([poses[c][0] for c in camera_of])
    t = np.stack([poses[c][1] for c in camera_of])
    uv = np.stack([project(truth[f], K, R[f], t[f])[0] for f in range(F)])
    uv += np.random.default_rng(seed).normal(0.0, noise_px, uv.shape)
    frames = np.zeros(F, dtype=np.int64)
    for c in range(cameras):
        frames[camera_of == c] = np.arange(np.sum(camera_of == c))
    problem = Problem(
        video_names=[f"cam{c}" for c in range(cameras)],
        video_index=np.asarray(camera_of),
        frames=frames,
        times=times.copy(),
        point_names=[f"p{i}" for i in range(P)],
        K=np.repeat(K[None], F, axis=0),
        R=R,
        t=t,
        dist=[None] * F,
        uv=uv,
    )
    return problem, truth


def round_robin(count: int, rate_hz: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Captures at `rate_hz` overall, each by one camera, never the same camera twice in a row."""
    rng = np.random.default_rng(seed)
    camera_of = np.zeros(count, dtype=np.int64)
    for k in range(1, count):
        camera_of[k] = (camera_of[k - 1] + rng.integers(1, 4)) % 4
    return np.arange(count) / rate_hz, camera_of


def start_points(problem: Problem, truth: np.ndarray, seed: int = 1, error_mm: float = 30.0) -> np.ndarray:
    """A poor start: the truth displaced by `error_mm` Gaussian noise per coordinate."""
    return truth + np.random.default_rng(seed).normal(0.0, error_mm, truth.shape)


def error_mm(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(estimate - truth, axis=-1)
