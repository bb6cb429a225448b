"""Do the cameras face what they track? A refusal, before any solve, of poses stored the other way round.

cameras.json stores cam_from_world (x_cam = R x_world + t). A calibration exported as world_from_cam (R^T, -R^T t),
or a camera turned 180 degrees, puts the tracked points behind the camera: two videos' rays of one point then meet
behind one of them, which no motion explains. The solver would find no frame to start from and fail deep inside;
here the video is named instead. Rays of two videos aimed at one subject meet near it, in front of both, whatever
their clocks (a point seen at different instants is still near the subject), so the test needs no timing.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import closest_depths

SAMPLES = 8  # observations of a point per pair of videos
MIN_PAIRS = 20  # ray pairs a video needs before it is judged
MIN_IN_FRONT = 0.25  # share of its ray pairs that meet in front of both cameras, below which it is refused
MIN_ANGLE_DEG = 1.0  # nearly parallel rays meet anywhere: not counted


def check_facing(problem: Problem, source: Path | str) -> None:
    """Raise InputError naming `source` (the cameras file) and the videos whose rays meet the other videos' behind
    a camera in most ray pairs (see the module docstring)."""
    first, second = _ray_pairs(problem)
    if not len(first):
        return
    front, usable = _in_front(problem, first, second)
    N = len(problem.video_names)
    total = np.zeros(N)
    good = np.zeros(N)
    for frames in (first, second):
        v = problem.video_index[frames[usable, 0]]
        np.add.at(total, v, 1.0)
        np.add.at(good, v, front[usable].astype(float))
    judged = total >= MIN_PAIRS
    share = np.divide(good, total, out=np.ones(N), where=total > 0)
    bad = np.flatnonzero(judged & (share < MIN_IN_FRONT))
    if not len(bad):
        return
    names = ", ".join(f"{problem.video_names[v]} ({100 * share[v]:.0f} %)" for v in bad)
    raise InputError(
        source,
        f"the tracked points lie behind the camera of {names}: the share of its rays that meet another video's "
        "ray of the same point in front of both cameras",
        fix="cameras.json stores cam_from_world (x_cam = R x_world + t): a pose given as world_from_cam "
        "(R^T, -R^T t) or a camera turned around does this; check the calibration's convention",
    )


def _ray_pairs(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) (frame, point) of one video and (M, 2) of another: up to SAMPLES observations of each point per pair
    of videos, spread over their frames, paired in order."""
    observed = problem.observed
    N = len(problem.video_names)
    first: list[np.ndarray] = []
    second: list[np.ndarray] = []
    for p in range(problem.num_points):
        per_video = [np.flatnonzero(observed[:, p] & (problem.video_index == v)) for v in range(N)]
        for v in range(N):
            for u in range(v + 1, N):
                n = min(len(per_video[v]), len(per_video[u]), SAMPLES)
                if n == 0:
                    continue
                for frames, out in ((per_video[v], first), (per_video[u], second)):
                    chosen = frames[np.linspace(0, len(frames) - 1, n).round().astype(np.int64)]
                    out.append(np.stack([chosen, np.full(n, p)], axis=1))
    if not first:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64)
    return np.concatenate(first), np.concatenate(second)


def _rays(problem: Problem, at: np.ndarray) -> np.ndarray:
    """(M, 3) unit world rays of the observations `at` (M, 2) (frame, point); lens distortion left out (a sign test)."""
    frames = at[:, 0]
    pixels = np.concatenate([problem.uv[frames, at[:, 1]], np.ones((len(at), 1))], axis=1)
    normalized = np.linalg.solve(problem.K[frames], pixels[..., None])[..., 0]
    directions = np.einsum("mji,mj->mi", problem.R[frames], normalized)  # R^T d
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _in_front(problem: Problem, first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) bool: the two rays' closest points lie in front of both cameras; and (M,) bool: the pair tells (not
    nearly parallel, both rays finite)."""
    centers = problem.centers
    r1, r2 = _rays(problem, first), _rays(problem, second)
    d1, d2, denom = closest_depths(r1, r2, centers[first[:, 0]] - centers[second[:, 0]])
    usable = denom >= math.sin(math.radians(MIN_ANGLE_DEG)) ** 2  # False for NaN too
    return (d1 > 0) & (d2 > 0), usable


__all__ = ["check_facing"]
