"""Isolated 2D spikes: one observation far from where its own track's neighbours put it (a false detection).

A detector's false detection, a tracker that jumped to another blob for one frame, or a mis-click is one
observation far off its track, with the frames before and after it where they should be. Such an observation
passes every image check, but the self-expressive solve fits whole shapes, so one false point damages the weights,
and through them the neighbouring frames. The screen runs per video and point, in frame order, and needs neither
the clocks nor the other videos: the observation is compared with the interpolation of its two neighbours (by
decoder time when the frames have one, else by frame number).

It is conservative, because a real sudden motion (a bounce, a hit) also leaves its neighbours' line: an
observation is set aside only when it is off that line by more than SPIKE_FRACTION of the image's diagonal and by
SPIKE_FACTOR times the track's typical deviation, and more than its neighbours are apart from each other. A spike is
also isolated in the body: where several points of one frame leave their lines together but not all of them (a jump
or a kick filmed at a low frame rate moves the legs between frames), the frame is real motion and keeps them. A
frame where every point jumps (the detector took another person) is still set aside.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from reconstruct.solver.problem import Problem

log = logging.getLogger(__name__)

SPIKE_FRACTION = 0.05  # of the image diagonal: off the neighbours' line by more than a fast real motion moves
SPIKE_FACTOR = 10.0  # times the track's median deviation
MIN_TRACK = 5  # observations a track needs before its typical deviation means anything
TOGETHER = 4  # this many points of one frame off their lines at once, in one direction, move as a body...
COHERENT = 0.7  # ... when their off-line directions agree this well (length of the mean unit vector)...
WHOLE_FRAME = 0.75  # ... unless they are this share of the frame's observed points or more (another person)


def find_spikes(problem: Problem) -> np.ndarray:
    """(F, P) bool: observations that are isolated spikes of their own video's track."""
    spikes = np.zeros(problem.observed.shape, dtype=bool)
    off = np.zeros(problem.uv.shape)  # (F, P, 2) px, each observation minus its neighbours' line
    diagonal = np.hypot(2 * problem.K[:, 0, 2], 2 * problem.K[:, 1, 2])  # (F,) from the principal point
    for video in range(len(problem.video_names)):
        rows = np.flatnonzero(problem.video_index == video)
        rows = rows[np.argsort(problem.frames[rows])]
        clock = problem.times[rows]
        clock = clock if np.all(np.isfinite(clock)) else problem.frames[rows].astype(float)
        for p in range(problem.num_points):
            seen = rows[problem.observed[rows, p]]
            if len(seen) < MIN_TRACK:
                continue
            at = clock[np.searchsorted(rows, seen)]
            flagged, off[seen, p] = _track_spikes(problem.uv[seen, p], at, float(np.median(diagonal[seen])))
            spikes[seen[flagged], p] = True
    body = _moving_together(spikes, off, problem.observed)
    if body.any():
        first = int(np.flatnonzero(body)[0])
        log.info(
            "%d frame(s) where %d or more points leave their tracks together, in one direction, kept as real "
            "motion (first: video %r frame %d, %d points)",
            int(body.sum()),
            TOGETHER,
            problem.video_names[problem.video_index[first]],
            int(problem.frames[first]),
            int(spikes[first].sum()),
        )
    spikes[body] = False
    return spikes


def _moving_together(spikes: np.ndarray, off: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(F,) bool: frames whose flagged points leave their lines as a body does (module docstring)."""
    count = spikes.sum(axis=1)
    candidates = np.flatnonzero((count >= TOGETHER) & (count < WHOLE_FRAME * observed.sum(axis=1)))
    body = np.zeros(len(spikes), dtype=bool)
    for f in candidates:
        vectors = off[f, spikes[f]]
        unit = vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)
        body[f] = bool(np.linalg.norm(unit.mean(axis=0)) >= COHERENT)
    return body


def _track_spikes(uv: np.ndarray, at: np.ndarray, diagonal: float) -> tuple[np.ndarray, np.ndarray]:
    """uv: (N, 2) one track in frame order, at: (N,) its clock -> (N,) bool spikes, and (N, 2) px each observation
    minus the line through its neighbours (at the ends: the extrapolation from the next two)."""
    deviation, apart = _off_line(uv[:-2], uv[1:-1], uv[2:], at[:-2], at[1:-1], at[2:])  # (N - 2, 2), (N - 2,)
    distance = np.linalg.norm(deviation, axis=1)
    limit = max(SPIKE_FRACTION * diagonal, SPIKE_FACTOR * float(np.median(distance)))
    flagged = np.zeros(len(uv), dtype=bool)
    flagged[1:-1] = (distance > limit) & (distance > apart)
    off = np.zeros((len(uv), 2))
    off[1:-1] = deviation
    # An end has one side only: its extrapolation from the next two is looser, so it must be twice as far off.
    for end, a, b in ((0, 1, 2), (len(uv) - 1, len(uv) - 2, len(uv) - 3)):
        vector, step = _off_line(
            uv[a][None], uv[end][None], uv[b][None], at[a : a + 1], at[end : end + 1], at[b : b + 1]
        )
        off[end] = vector[0]
        far = float(np.linalg.norm(vector[0]))
        flagged[end] = bool(far > 2 * limit and far > 2 * step[0] and not flagged[a])
    return flagged, off


def _off_line(
    first: np.ndarray, middle: np.ndarray, last: np.ndarray, t0: np.ndarray, t1: np.ndarray, t2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) positions at times t0, t1, t2 (M,) -> `middle` minus the line through `first` and `last` at t1 (inter-
    or extrapolated), (M, 2), and the distance between `first` and `last`, (M,)."""
    span = t2 - t0
    weight = np.where(span != 0, (t1 - t0) / np.where(span != 0, span, 1.0), 0.5)[:, None]
    return middle - (first + weight * (last - first)), np.linalg.norm(last - first, axis=1)


def remove_spikes(problem: Problem) -> tuple[Problem, int]:
    """The problem without its isolated spikes (set to NaN: unobserved), and how many there were."""
    spikes = find_spikes(problem)
    count = int(spikes.sum())
    if not count:
        return problem, 0
    uv = problem.uv.copy()
    uv[spikes] = np.nan
    f, p = np.argwhere(spikes)[0]
    log.warning(
        "%d observation(s) set aside as isolated 2D spikes, far from their own track's neighbours (a false "
        "detection or a tracker jump; first: video %r frame %d point %r)",
        count,
        problem.video_names[problem.video_index[f]],
        int(problem.frames[f]),
        problem.point_names[p],
    )
    return replace(problem, uv=uv), count


__all__ = ["find_spikes", "remove_spikes"]
