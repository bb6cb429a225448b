"""How many videos see a point near each instant: a position along one camera's rays alone has no depth.

The solver gives every (frame, point) a position, also where a single video saw the point around that instant:
there the depth comes from the motion model alone, and on real captures such positions were metres off (a ball one
camera saw in one frame, the other in all of them), some behind or on the camera that saw them. `views_near`
counts, for every (frame, point), the distinct videos that observe the point within `WINDOW_PERIODS` frame periods
of the frame's global time (the frame's own video included); fewer than two is `SINGLE_VIEW`.
"""

from __future__ import annotations

import numpy as np

from reconstruct.clocks.model import frame_periods
from reconstruct.outputs.points import SINGLE_VIEW  # fewer videos near an instant: the depth there is not measured

WINDOW_PERIODS = 2.0  # the window, in frame periods of the slower of the two videos compared
HOOD_CELLS = 2**24  # booleans per pass of the neighbourhood count (memory)


def views_near(
    video_index: np.ndarray, times: np.ndarray, observed: np.ndarray, hood: np.ndarray | None = None
) -> np.ndarray:
    """(F, P) the distinct videos observing each point within `WINDOW_PERIODS` frame periods of each frame's time.

    video_index: (F,) each frame's video; times: (F,) global times in s (NaN where a video's clock is unknown);
    observed: (F, P) bool; hood: (F, n) frame indices (-1 padded) of each frame and its self-expression
    neighbours (`trust.neighbourhoods`), which stand in for the window where a video has no clock: then every
    frame takes the larger of its count by time and the videos among its neighbours that observe the point
    (None: a frame without a time counts its own video only)."""
    observed = np.asarray(observed, dtype=bool)
    F, P = observed.shape
    N = int(video_index.max()) + 1 if F else 0
    periods = frame_periods(times, video_index, N)
    timed = np.isfinite(times)
    count = np.zeros((F, P), dtype=np.int64)
    for u in range(N):
        rows = np.flatnonzero((video_index == u) & timed)
        # a video of one timed frame has no period: 0, so that its own observation (and one at its instant) counts
        window = WINDOW_PERIODS * np.maximum(np.nan_to_num(periods[u]), np.nan_to_num(periods[video_index]))
        for p in range(P):
            seen = np.sort(times[rows[observed[rows, p]]])
            if seen.size:
                count[:, p] += nearest_gap(seen, times) <= window
    if timed.all():
        return count
    # A video without a clock has no observation at a known time: every frame, timed or not, also counts the videos
    # of its neighbours in the solve that observe the point (a timed frame would otherwise never see that video).
    count[~timed] = observed[~timed]
    if hood is not None:
        count = np.maximum(count, _hood_views(video_index, observed, hood, N))
    return count


def _hood_views(video_index: np.ndarray, observed: np.ndarray, hood: np.ndarray, N: int) -> np.ndarray:
    """(M, P) distinct videos among the frames of `hood` (M, n; -1 padded) that observe each point."""
    out = np.zeros((hood.shape[0], observed.shape[1]), dtype=np.int64)
    chunk = max(1, HOOD_CELLS // max(1, observed.shape[1] * N))  # rows per pass: (rows, P, N) booleans at a time
    for start in range(0, hood.shape[0], chunk):
        part = hood[start : start + chunk]
        seen = np.zeros((part.shape[0], observed.shape[1], N), dtype=bool)
        rows = np.arange(part.shape[0])
        for k in range(part.shape[1]):
            valid = part[:, k] >= 0
            frames = part[valid, k]
            seen[rows[valid], :, video_index[frames]] |= observed[frames]
        out[start : start + chunk] = seen.sum(axis=-1)
    return out


def nearest_gap(seen: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(F,) the distance from each time to the nearest of the sorted `seen` times (NaN for a NaN time)."""
    at = np.clip(np.searchsorted(seen, times), 1, max(seen.size - 1, 1))
    if seen.size == 1:
        return np.abs(times - seen[0])
    return np.minimum(np.abs(times - seen[at - 1]), np.abs(seen[at] - times))


__all__ = ["SINGLE_VIEW", "WINDOW_PERIODS", "nearest_gap", "views_near"]
