"""The referee of the tracks path beyond a few points (issue 22): the self-expressive solve on a subsample of the
frames, whose W links give every video's clock without the track search; the tracks' clocks are used only where
both agree (docs/refinement.md, "The referee").

The track search alone can lock a periodic motion a whole cycle off (the video sample's walk: one stride), while
W's links, which compare whole shapes of every point, tell the cycles apart. Solving every REFEREE_STEP-th frame
(and, in long captures, only a window of REFEREE_FRAMES of them around the middle of the tracks' global time) costs
a fraction of the full seed solve, and a clock a cycle off disagrees by far more than the subsample's frame period.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from typing import Any

import numpy as np

from dynrecon.errors import DynreconError
from dynrecon.jsonvalues import finite_or_none
from reconstruct.clocks.estimate import ClockOptions, SearchMode, estimate_clocks
from reconstruct.clocks.model import Clocks, frame_periods
from reconstruct.solver.alternation import SolverOptions, solve
from reconstruct.solver.problem import Problem
from reconstruct.time_checks import Check

log = logging.getLogger(__name__)

REFEREE_STEP = 3  # every REFEREE_STEP-th frame of each video
# At most this many subsampled frames: beyond, those nearest the middle of the tracks' global time (a window far
# longer than one cycle of a human motion, so that a frame's true counterpart in another video is inside it: with
# 4 videos, ~225 frames of each). Its solve then costs about what the track search and the refinement it runs
# beside cost, so that the verdict seldom waits.
REFEREE_FRAMES = 300
# The clocks agree where every video's median difference (relative to the reference video) is within this many
# subsampled frame periods of the slowest video: a W link resolves a time no finer than the spacing of the frames
# it links, and a wrong cycle is many periods off.
REFEREE_PERIODS = 1.0


def referee_check(
    problem: Problem, clocks: Clocks, solver: SolverOptions, clock_options: ClockOptions
) -> tuple[Check, dict[str, Any]]:
    """Whether the seed solve's W clocks on a subsample agree with the tracks' `clocks` (the check, and the
    report's `referee` entry: frames solved, per-video differences in s and subsampled periods, seconds)."""
    started = time.perf_counter()
    index = subsample(problem, clocks.global_time)
    referee_time = referee_times(problem, index, solver, clock_options)
    return compare(problem, clocks, index, referee_time, time.perf_counter() - started)


def referee_times(
    problem: Problem, index: np.ndarray, solver: SolverOptions, clock_options: ClockOptions
) -> np.ndarray:
    """(F',) global times of frames `index` from the seed solve's W links on those frames alone (NaN where a video
    is not identified, or everywhere when the subsample cannot be solved)."""
    sub = take_frames(problem, index)
    try:
        seed = solve(sub, solver)
        # W's links alone: the track search is what is being checked
        return estimate_clocks(sub, seed, replace(clock_options, search=SearchMode.NEVER)).global_time
    except (DynreconError, np.linalg.LinAlgError, ValueError) as error:
        # too little in the subsample to solve, or a degenerate one: nothing confirms the tracks' clocks, and the
        # full seed solve that follows says what is wrong with the data, if anything
        log.info("tracks path referee: no solve on %d frames (%s)", index.size, error)
        return np.full(index.size, np.nan)


def compare(
    problem: Problem, clocks: Clocks, index: np.ndarray, referee_time: np.ndarray, seconds: float
) -> tuple[Check, dict[str, Any]]:
    """The check of the tracks' `clocks` against the referee's times of frames `index` (`referee_times`, which took
    `seconds`), and the report's entry."""
    sub_videos = problem.video_index[index]
    difference = referee_time - clocks.global_time[index]  # (F',) s, both in the reference's gauge
    reference = problem.video_names.index(clocks.reference)
    ref_shift = _median(difference[sub_videos == reference])
    periods = frame_periods(clocks.global_time, problem.video_index, len(problem.video_names))
    finite = periods[np.isfinite(periods)]
    scale = REFEREE_STEP * float(finite.max()) if finite.size else math.nan  # the slowest video's subsampled period
    per_video: dict[str, Any] = {}
    worst = 0.0
    for v, name in enumerate(problem.video_names):
        shift = _median(difference[sub_videos == v]) - ref_shift
        off = abs(shift) / scale if math.isfinite(shift) and scale > 0 else math.inf
        if np.any(sub_videos == v):
            worst = max(worst, off)
            per_video[name] = {"difference_s": shift if math.isfinite(shift) else None, "periods": finite_or_none(off)}
    check = Check(
        name="referee",
        value=worst,
        limit=REFEREE_PERIODS,
        passed=bool(worst <= REFEREE_PERIODS),
        meaning=(
            f"largest clock difference to the seed solve's W links on every {REFEREE_STEP}th frame "
            "(subsampled frame periods of the slowest video)"
        ),
    )
    report = {
        "frames": int(index.size),
        "step": REFEREE_STEP,
        "videos": per_video,
        "seconds": seconds,
    }
    log.info(
        "tracks path referee: the seed solve on %d frames %s the tracks' clocks (largest difference %.2g periods)",
        index.size,
        "agrees with" if check.passed else "disagrees with",
        worst,
    )
    return check, report


def subsample(problem: Problem, global_time: np.ndarray) -> np.ndarray:
    """(F',) sorted frame indices: every REFEREE_STEP-th frame of each video, and of those at most REFEREE_FRAMES,
    the nearest to the middle of `global_time (F,)`."""
    index = _every_step(problem)
    if index.size > REFEREE_FRAMES:
        timed = np.isfinite(global_time[index])
        middle = float(np.median(global_time[index[timed]])) if timed.any() else 0.0
        distance = np.where(timed, np.abs(global_time[index] - middle), np.inf)
        index = np.sort(index[np.argsort(distance, kind="stable")[:REFEREE_FRAMES]])
    return index


def subsample_without_clocks(problem: Problem) -> np.ndarray | None:
    """`subsample`'s frames where they do not depend on the clocks (no window needed), else None."""
    index = _every_step(problem)
    return index if index.size <= REFEREE_FRAMES else None


def _every_step(problem: Problem) -> np.ndarray:
    """(F',) every REFEREE_STEP-th frame of each video (by frame number), sorted."""
    rank = np.zeros(problem.num_frames, dtype=np.int64)
    for v in range(len(problem.video_names)):
        own = np.flatnonzero(problem.video_index == v)
        rank[own[np.argsort(problem.frames[own], kind="stable")]] = np.arange(own.size)
    return np.flatnonzero(rank % REFEREE_STEP == 0)


def take_frames(problem: Problem, index: np.ndarray) -> Problem:
    """The problem restricted to frames `index (F',)` (same videos and points)."""
    return Problem(
        video_names=problem.video_names,
        video_index=problem.video_index[index],
        frames=problem.frames[index],
        times=problem.times[index],
        point_names=problem.point_names,
        K=problem.K[index],
        R=problem.R[index],
        t=problem.t[index],
        dist=[problem.dist[i] for i in index],
        uv=problem.uv[index],
    )


def _median(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else math.nan
