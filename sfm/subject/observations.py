"""Per-video observation arrays from `Tracks`: pixels, undistorted normalized coordinates, time interpolation."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from sfm.subject.model import SubjectVideo
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class VideoObs:
    name: str
    video: SubjectVideo
    times: np.ndarray  # (F,) own seconds
    period: float  # the tracks' sampling period (s): the median step between tracked frames, at least a frame
    xy: np.ndarray  # (F, P, 2) pixels, NaN = unobserved
    norm: np.ndarray  # (F, P, 2) undistorted normalized coordinates with `K` (a guess when not known)
    K: np.ndarray  # (3, 3) known or current estimate
    known_K: bool  # noqa: N815 (K is the paper's name)
    dist: np.ndarray | None  # known distortion (applied when undistorting), None = none

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    @property
    def video_centre(self) -> np.ndarray:
        return np.array([(self.video.width - 1) / 2, (self.video.height - 1) / 2])  # (2,) pixels

    def count(self) -> int:
        return int(np.isfinite(self.xy[..., 0]).sum())

    def set_focal(self, f: float) -> None:
        """Re-normalize with a new focal estimate (unknown K only; the principal point stays at the centre)."""
        self.K = np.array([[f, 0, self.K[0, 2]], [0, f, self.K[1, 2]], [0, 0, 1.0]])
        self.norm = normalize(self.xy, self.K, self.dist)


def guess_K(video: SubjectVideo) -> np.ndarray:  # noqa: N802
    f = 1.2 * max(video.width, video.height)  # a guess: a field of view of about 45° across the long side
    return np.array([[f, 0, (video.width - 1) / 2], [0, f, (video.height - 1) / 2], [0, 0, 1.0]])


def normalize(xy: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """xy: (..., 2) pixels (NaN kept) -> (..., 2) undistorted normalized coordinates."""
    flat = xy.reshape(-1, 2)
    out = np.full_like(flat, np.nan)
    ok = np.isfinite(flat[:, 0])
    if ok.any():
        # OpenCV's default iterations, not dynrecon.lens: the path's self-calibrated polynomial lenses can fold
        # beyond the tracked region, and iterated to convergence they moved its noise choice (docs/measurements.md)
        d = None if dist is None else np.asarray(dist, dtype=float)
        out[ok] = cv2.undistortPoints(flat[ok].reshape(-1, 1, 2).astype(np.float64), K, d).reshape(-1, 2)
    return out.reshape(xy.shape)


def build_observations(tracks: Tracks, videos: list[SubjectVideo]) -> tuple[list[str], list[VideoObs]]:
    """Observation arrays of every video (in `videos` order) over the union of point names (sorted: the result
    does not depend on the tracks' row order)."""
    points = sorted(tracks.point_names())
    p_index = {p: i for i, p in enumerate(points)}
    v_index = {v.name: i for i, v in enumerate(videos)}
    vid = np.array([v_index.get(v, -1) for v in tracks.video], dtype=np.int64)  # (N,)
    pid = np.array([p_index[p] for p in tracks.point], dtype=np.int64)  # (N,)
    unknown = sorted(set(tracks.video) - set(v_index))
    if unknown:
        log.warning("tracks of unknown video(s) %s are ignored", ", ".join(unknown))
    out: list[VideoObs] = []
    for i, video in enumerate(videos):
        times = np.asarray(video.times, dtype=float)
        xy = np.full((len(times), len(points), 2), np.nan)
        rows = np.nonzero(vid == i)[0]
        frames = tracks.frame[rows]
        inside = (frames >= 0) & (frames < len(times)) & np.isfinite(tracks.xy[rows]).all(1)
        if (~inside).any():
            log.warning(
                "video %s: %d observation(s) beyond its %d frames are ignored",
                video.name,
                int((~inside).sum()),
                len(times),
            )
        rows, frames = rows[inside], frames[inside]
        xy[frames, pid[rows]] = tracks.xy[rows]
        period = sampling_period(times, xy)
        known = video.K is not None
        K = np.asarray(video.K, dtype=float) if known else guess_K(video)
        dist = np.asarray(video.dist, dtype=float) if video.dist is not None else None
        out.append(
            VideoObs(
                name=video.name,
                video=video,
                times=times,
                period=period,
                xy=xy,
                norm=normalize(xy, K, dist),
                K=K,
                known_K=known,
                dist=dist,
            )
        )
    return points, out


def sampling_period(times: np.ndarray, xy: np.ndarray) -> float:
    """Seconds between the tracks' samples: the median step between frames with an observation (tracks of every
    4th frame of a 120 fps video: 1/30 s), at least the median frame period."""
    frame = float(np.median(np.diff(times))) if len(times) > 1 else 1.0 / 30
    tracked = times[np.isfinite(xy[..., 0]).any(axis=1)]  # (F',) times of the frames with any observation
    steps = np.diff(tracked)
    return max(frame, float(np.median(steps))) if len(steps) else frame


def interpolate(values: np.ndarray, times: np.ndarray, query: np.ndarray, max_gap: float) -> np.ndarray:
    """Linear interpolation in time of each point's samples.

    values: (F, P, C) with NaN = unobserved, times: (F,) increasing, query: (...) seconds -> (..., P, C); NaN where
    the query is not between two observed samples of that point at most `max_gap` apart.
    """
    F, P, _C = values.shape
    obs = np.isfinite(values[..., 0])  # (F, P)
    idx = np.broadcast_to(np.arange(F)[:, None], (F, P))
    prev = np.maximum.accumulate(np.where(obs, idx, -1), axis=0)  # (F, P) last observed frame <= f
    nxt = np.minimum.accumulate(np.where(obs, idx, F)[::-1], axis=0)[::-1]  # (F, P) first observed frame >= f
    nxt = np.concatenate([nxt, np.full((1, P), F)])  # (F + 1, P) so that j + 1 = F is valid
    j = np.searchsorted(times, query, side="right") - 1  # (...) times[j] <= q < times[j + 1]
    inside = (j >= 0) & (j < F)
    jc = np.clip(j, 0, F - 1)
    p0 = prev[jc]  # (..., P)
    n1 = nxt[jc + 1]  # (..., P)
    # an exact hit on an observed frame needs no partner
    exact = (p0 == jc[..., None]) & (times[jc] == query)[..., None]
    n1 = np.where(exact, p0, n1)
    ok = inside[..., None] & (p0 >= 0) & (n1 < F)
    p0c, n1c = np.clip(p0, 0, F - 1), np.clip(n1, 0, F - 1)
    t0, t1 = times[p0c], times[n1c]
    ok &= (t1 - t0) <= max_gap
    w = np.where(t1 > t0, (query[..., None] - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)  # (..., P)
    cols = np.arange(P)
    out = (1 - w)[..., None] * values[p0c, cols] + w[..., None] * values[n1c, cols]
    out[~ok] = np.nan
    return out
