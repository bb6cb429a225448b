"""Frames where no reconstructable point is observed: left out of the alternation, then put back.

Such a frame has no ray term: its shape is free in the self-expression (only the smoothness term pulls it), so it
adds unknowns that the data do not determine and slows the X-step's iterations (detections every n-th frame, or a
subject lost for a stretch, leave most frames so; docs/measurements.md). The solve runs on the other frames; the
left-out ones get their video's neighbouring shapes interpolated (as the solver's start fills missing points), no
W links and no self-expression residual.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from reconstruct.solver.initialize import PairInit, fill_missing_points
from reconstruct.solver.problem import Problem
from reconstruct.solver.wstep import SparseW


def seen_frames(problem: Problem, keep: np.ndarray) -> np.ndarray:
    """(F,) bool: the frames where at least one of the `keep` (P,) points is observed."""
    return np.asarray(problem.observed[:, keep].any(axis=1))


def take_frames(problem: Problem, frames: np.ndarray) -> Problem:
    """The problem on `frames` (F,) bool, in the same order; videos left without a frame are dropped."""
    index = np.flatnonzero(frames)
    present = np.unique(problem.video_index[index])
    renumber = np.full(len(problem.video_names), -1, dtype=np.int64)
    renumber[present] = np.arange(len(present))
    return dataclasses.replace(
        problem,
        video_names=[problem.video_names[v] for v in present],
        video_index=renumber[problem.video_index[index]],
        frames=problem.frames[index],
        times=problem.times[index],
        K=problem.K[index],
        R=problem.R[index],
        t=problem.t[index],
        dist=[problem.dist[i] for i in index],
        uv=problem.uv[index],
    )


def put_back(points: np.ndarray, frames: np.ndarray, video_index: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(F, P, 3) from the solved frames' (F', P, 3): the other frames interpolated within their video over frame
    order (edges held; a video without a solved frame gets each point's mean), the `keep` points only."""
    out = along(points, frames)
    out[:, keep] = fill_missing_points(out[:, keep], video_index)
    return out


def put_back_w(W: SparseW, frames: np.ndarray) -> SparseW:
    """W over every frame: the solved frames' columns, their candidates renumbered; none for the others."""
    index = np.flatnonzero(frames)
    F, K = len(frames), W.cand.shape[1]
    cand, valid, value = np.zeros((F, K), dtype=W.cand.dtype), np.zeros((F, K), dtype=bool), np.zeros((F, K))
    cand[index], valid[index], value[index] = index[W.cand], W.valid, W.value
    return SparseW(cand=cand, valid=valid, value=value)


def put_back_init(init: PairInit, frames: np.ndarray) -> PairInit:
    """The initialization over every frame: no partner, cost or depth for the left-out ones."""
    index = np.flatnonzero(frames)
    partner = np.full(len(frames), -1, dtype=init.partner.dtype)
    partner[index] = np.where(init.partner >= 0, index[np.maximum(init.partner, 0)], -1)
    return PairInit(partner=partner, cost=along(init.cost, frames), depth=along(init.depth, frames))


def along(values: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(F, ...) from the solved frames' values, NaN for the others."""
    out = np.full((len(frames), *values.shape[1:]), np.nan)
    out[frames] = values
    return out


__all__ = ["along", "put_back", "put_back_init", "put_back_w", "seen_frames", "take_frames"]
