"""The solver's input arrays: per frame a pose, intrinsics, time and the 2D observations of every point.

Frame order: videos in cameras.json order, frames of a video by frame number. Everything downstream indexes frames
0..F-1 in this order. `reconstruct.inputs.build_problem` makes one from the contract files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(kw_only=True)
class Problem:
    """All posed frames and their 2D observations."""

    video_names: list[str]  # (N,) videos in order
    video_index: np.ndarray  # (F,) index into video_names
    frames: np.ndarray  # (F,) frame number within its video
    times: np.ndarray  # (F,) decoder time in s, NaN when unknown
    point_names: list[str]  # (P,)
    K: np.ndarray  # (F, 3, 3)
    R: np.ndarray  # (F, 3, 3) cam_from_world
    t: np.ndarray  # (F, 3) cam_from_world
    dist: list[np.ndarray | None]  # (F,) OpenCV distortion or None
    uv: np.ndarray  # (F, P, 2) pixels, NaN = unobserved

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def num_points(self) -> int:
        return len(self.point_names)

    @property
    def observed(self) -> np.ndarray:
        """(F, P) bool."""
        return ~np.isnan(self.uv[..., 0])

    @property
    def centers(self) -> np.ndarray:
        """(F, 3) camera centres in world coordinates."""
        return -np.einsum("fji,fj->fi", self.R, self.t)

    @property
    def frame_videos(self) -> list[str]:
        return [self.video_names[i] for i in self.video_index]


def reconstructable_points(problem: Problem) -> np.ndarray:
    """(P,) bool: points observed in at least two different videos (one video alone cannot fix depth)."""
    observed = problem.observed
    counts = np.zeros(problem.num_points, dtype=np.int64)
    for vi in range(len(problem.video_names)):
        counts += observed[problem.video_index == vi].any(axis=0)
    return counts >= 2


def most_observed(observed: np.ndarray, among: np.ndarray, count: int) -> np.ndarray:
    """(P,) bool: of the points `among (P,)`, the `count` with the most observations in `observed (F, P)` (ties in
    point order)."""
    seen = np.where(among, observed.sum(axis=0), -1)
    chosen = np.zeros_like(among, dtype=bool)
    chosen[np.argsort(-seen, kind="stable")[:count]] = True
    return chosen & among
