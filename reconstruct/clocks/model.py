"""The clock model: how each video's own time maps to the one global time of a capture (docs/clocks.md).

A video's own time is its decoder time (cameras.json `time`), else frame / fps (`own_times`). Its clock maps own
time to global time, in seconds, as a polynomial about a centre (the middle of the video's own times, for
conditioning):

    global = a + b s + c s^2,    s = own - center

`ClockModel` says which terms are free: OFFSET (a; b = 1, c = 0), AFFINE (a, b) or DRIFT (a, b, c). The gauge is a
reference video whose clock is the identity (global = own). The same clock is reported at own time 0:
global = offset + rate own + drift own^2 (`Clock.offset_rate_drift`).

- `Clock`: one video's clock, its inverse (global -> own) and its uncertainty (covariance of a, b, c);
- `ClockSet`: the clocks of all videos side by side, the form the link fit and the track search estimate;
- `ClockCorrection`: a small offset and rate change of every clock on the global time axis (the clock polish);
- `VideoClockReport` and `Clocks`: the recovered clocks as reported, and their JSON form (sequencing.json `clocks`,
  report.json `clocks`).

The simulator's true clocks (`simulation.phones.TrueClock`) are `Clock`s too.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.errors import InputError
from dynrecon.jsonvalues import finite_or_none, float_or_nan
from reconstruct.solver.problem import Problem

DEFAULT_FPS = 30.0  # own time of a video without decoder times or a known frame rate (its rate absorbs the error)


class ClockModel(enum.Enum):
    OFFSET = "offset"  # rate fixed to 1 (decoder times assumed exact)
    AFFINE = "affine"  # offset and rate
    DRIFT = "drift"  # offset, rate and a quadratic drift

    @property
    def free_terms(self) -> int:
        """How many of (a, b, c) the fits estimate; the others keep b = 1, c = 0."""
        return {ClockModel.OFFSET: 1, ClockModel.AFFINE: 2, ClockModel.DRIFT: 3}[self]

    @property
    def refit_degree(self) -> int:
        """Polynomial degree of a clock refitted to given times: offset clocks report the rate those times imply."""
        return 2 if self is ClockModel.DRIFT else 1


class TimeSource(enum.Enum):
    DECODER = "decoder"  # decoder timestamps of cameras.json
    FPS = "fps"  # frame / fps with a known frame rate
    NOMINAL = "nominal"  # frame / DEFAULT_FPS: the rate of this video carries its unknown frame rate


# ---------------------------------------------------------------------------------------------------------------
# One clock


@dataclass(kw_only=True)
class Clock:
    """One video's clock: global = a + b s + c s^2 with s = own - center (s); `cov` over (a, b, c), 0 when fixed."""

    center: float = 0.0
    coef: np.ndarray  # (3,) a, b, c
    cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # (3, 3), NaN when unknown

    @classmethod
    def affine(cls, offset: float, rate: float) -> Clock:
        """global = offset + rate * own, exactly (centre 0)."""
        return cls(center=0.0, coef=np.array([offset, rate, 0.0]))

    @classmethod
    def identity(cls, center: float) -> Clock:
        """global = own: the reference video's clock (a = center, b = 1, c = 0)."""
        return cls(center=center, coef=np.array([center, 1.0, 0.0]))

    def global_time(self, own: np.ndarray) -> np.ndarray:
        s = np.asarray(own, dtype=float) - self.center
        return self.coef[0] + self.coef[1] * s + self.coef[2] * s * s

    def own_time(self, global_time: np.ndarray) -> np.ndarray:
        """Inverse of `global_time`: the affine solution, then Newton steps when the clock has a drift term."""
        a, b, c = self.coef
        s = (global_time - a) / b
        for _ in range(3 if c != 0 else 0):
            s -= (a + b * s + c * s * s - global_time) / (b + 2 * c * s)
        return s + self.center

    def offset_rate_drift(self) -> tuple[np.ndarray, np.ndarray]:
        """(offset, rate, drift) at own time 0 and their stds."""
        m = self.center
        T = np.array([[1.0, -m, m * m], [0.0, 1.0, -2.0 * m], [0.0, 0.0, 1.0]])
        values = T @ self.coef
        cov = T @ self.cov @ T.T
        return values, np.sqrt(np.maximum(np.diag(cov), 0.0))


# ---------------------------------------------------------------------------------------------------------------
# The clocks of all videos


def clock_basis(s: np.ndarray) -> np.ndarray:
    """(n, 3) the terms (1, s, s^2) of the clock polynomial at centred own times s (n,)."""
    return np.stack([np.ones_like(s), s, s * s], axis=1)


@dataclass(kw_only=True)
class ClockSet:
    """The clocks of N videos: video v's is Clock(center[v], coef[v], cov[v]), used only where identified[v]."""

    center: np.ndarray  # (N,)
    coef: np.ndarray  # (N, 3)
    cov: np.ndarray  # (N, 3, 3), NaN for unidentified videos
    identified: np.ndarray  # (N,) bool

    @classmethod
    def reference_only(cls, center: np.ndarray, ref: int) -> ClockSet:
        """Every clock unknown but the reference's, which is the identity (exact)."""
        N = len(center)
        clocks = cls(
            center=center,
            coef=np.full((N, 3), np.nan),
            cov=np.full((N, 3, 3), np.nan),
            identified=np.zeros(N, dtype=bool),
        )
        clocks.coef[ref] = Clock.identity(center[ref]).coef
        clocks.cov[ref] = 0.0
        clocks.identified[ref] = True
        return clocks

    def clock(self, v: int) -> Clock:
        return Clock(center=self.center[v], coef=self.coef[v], cov=self.cov[v])

    def global_time(self, own: np.ndarray, video_index: np.ndarray) -> np.ndarray:
        """(F,) global time of frames at own times (F,) of videos video_index (F,)."""
        s = own - self.center[video_index]
        c = self.coef[video_index]
        return c[:, 0] + c[:, 1] * s + c[:, 2] * s * s

    def global_std(self, own: np.ndarray, video_index: np.ndarray) -> np.ndarray:
        """(F,) std of `global_time` from the clocks' covariance."""
        basis = clock_basis(own - self.center[video_index])
        var = np.einsum("fi,fij,fj->f", basis, self.cov[video_index], basis)
        return np.sqrt(np.maximum(var, 0.0))

    def offset_rate_drift(self, v: int) -> tuple[np.ndarray, np.ndarray]:
        """Video v's (offset, rate, drift) at own time 0 and their stds."""
        return self.clock(v).offset_rate_drift()


# ---------------------------------------------------------------------------------------------------------------
# A correction of every clock on the global time axis


@dataclass(kw_only=True)
class ClockCorrection:
    """Each video's times moved by g' = g + offset + rate (g - middle): a small change of its clock's offset and rate
    expressed on global times (what the clock polish of the trajectory refinement estimates)."""

    middle: np.ndarray  # (N,) s, the global time each video's rate change turns about
    offset: np.ndarray  # (N,) s
    rate: np.ndarray  # (N,) relative

    @classmethod
    def none(cls, middle: np.ndarray) -> ClockCorrection:
        return cls(middle=middle, offset=np.zeros(len(middle)), rate=np.zeros(len(middle)))

    def apply(self, times: np.ndarray, video_index: np.ndarray) -> np.ndarray:
        """(F,) corrected global times of frames at `times (F,)` of videos `video_index (F,)`."""
        v = video_index
        return times + self.offset[v] + self.rate[v] * (times - self.middle[v])

    def in_gauge_of(
        self, reference: int, times: np.ndarray, video_index: np.ndarray
    ) -> tuple[np.ndarray, ClockCorrection]:
        """The corrected times and this correction after the affine map A(g) = (g - b) / a of global time that gives
        video `reference` its uncorrected clock back (a global affine change of time is the gauge)."""
        a = 1.0 + self.rate[reference]
        b = self.offset[reference] - self.rate[reference] * self.middle[reference]
        adjusted = (self.apply(times, video_index) - b) / a
        offset = (self.middle + self.offset - b) / a - self.middle
        rate = (1.0 + self.rate) / a - 1.0
        return adjusted, ClockCorrection(middle=self.middle, offset=offset, rate=rate)

    @classmethod
    def fit(cls, before: np.ndarray, after: np.ndarray, video_index: np.ndarray, num_videos: int) -> ClockCorrection:
        """The correction that maps global times `before (F,)` to `after (F,)`, by least squares per video about its
        median time (zero for a video with fewer than two distinct times)."""
        correction = cls.none(np.zeros(num_videos))
        for v in range(num_videos):
            own = video_index == v
            if own.sum() >= 2 and np.ptp(before[own]) > 0:
                middle = float(np.median(before[own]))
                slope, intercept = np.polyfit(before[own] - middle, after[own] - before[own], 1)
                correction.middle[v], correction.offset[v], correction.rate[v] = middle, intercept, slope
        return correction


# ---------------------------------------------------------------------------------------------------------------
# Own time


def own_times(problem: Problem, fps: Mapping[str, float] | None = None) -> tuple[np.ndarray, list[TimeSource]]:
    """(F,) own time of every frame in s, and the source per video.

    frame / fps for a video `fps` gives a rate (a rate given, not measured: its problem times, if any, are that
    rate's); else decoder times where given, a frame missing its time in a video that has times elsewhere placed on
    the line time ~ frame fitted to that video's times (registration may drop frames, decoders do not skip
    timestamps); else frame / DEFAULT_FPS.
    """
    fps = fps or {}
    own = np.full(problem.num_frames, np.nan)
    sources: list[TimeSource] = []
    for v, name in enumerate(problem.video_names):
        rows = np.flatnonzero(problem.video_index == v)
        frames = problem.frames[rows].astype(float)
        times = problem.times[rows]
        known = np.isfinite(times)
        if name in fps and fps[name] > 0:
            own[rows] = frames / fps[name]
            sources.append(TimeSource.FPS)
        elif known.sum() >= 2 and np.ptp(frames[known]) > 0:
            slope, intercept = np.polyfit(frames[known], times[known], 1)
            own[rows] = np.where(known, times, intercept + slope * frames)
            sources.append(TimeSource.DECODER)
        else:
            own[rows] = frames / DEFAULT_FPS
            sources.append(TimeSource.NOMINAL)
    return own, sources


def frame_periods(own: np.ndarray, video_index: np.ndarray, num_videos: int) -> np.ndarray:
    """(N,) median interval between consecutive frames of each video, s."""
    periods = np.full(num_videos, np.nan)
    for v in range(num_videos):
        t = np.sort(own[video_index == v])
        steps = np.diff(t)
        steps = steps[steps > 0]
        if len(steps):
            periods[v] = float(np.median(steps))
    return periods


def video_centers(own: np.ndarray, video_index: np.ndarray, num_videos: int) -> np.ndarray:
    """(N,) mean own time of each video (0 for a video without frames): the centres of the clock polynomials."""
    return np.array([np.mean(own[video_index == v]) if np.any(video_index == v) else 0.0 for v in range(num_videos)])


# ---------------------------------------------------------------------------------------------------------------
# The recovered clocks as reported


@dataclass(kw_only=True)
class VideoClockReport:
    """One video's recovered clock as reported: global = offset + rate * own + drift * own^2 (s); stds are 1-sigma,
    0 when fixed."""

    name: str
    time_source: TimeSource
    offset: float = math.nan
    rate: float = math.nan
    drift: float = 0.0
    offset_std: float = math.nan
    rate_std: float = math.nan
    drift_std: float = 0.0
    method: str = "unidentified"  # reference | links | tracks | combined | unidentified
    identified: bool = False
    links: int = 0  # inlier W links touching this video
    track_residual_px: float = math.nan  # robust RMS triangulation residual of its tracks (track search)
    frame_scatter: float = math.nan  # s, per-frame timing spread around the clock (jitter or floor), in time_std
    # offset_std as estimated, before a refit widened it by its move (`Clocks.refit`); NaN: offset_std is it. The
    # agreement with registered or declared offsets is judged on it, so that a moved clock is not looser there.
    estimate_std: float = math.nan

    def refit(self, own: np.ndarray, times: np.ndarray, model: ClockModel) -> None:
        """Offset, rate (and drift) fitted to global `times (n,)` at own times (n,) by least squares."""
        coefficients = np.polyfit(own, times, model.refit_degree)[::-1]
        self.offset, self.rate = float(coefficients[0]), float(coefficients[1])
        if model.refit_degree == 2:
            self.drift = float(coefficients[2])

    def to_json(self) -> dict[str, Any]:
        return {
            "video": self.name,
            "time_source": self.time_source.value,
            "method": self.method,
            "identified": self.identified,
            "offset": finite_or_none(self.offset),
            "offset_std": finite_or_none(self.offset_std),
            "rate": finite_or_none(self.rate),
            "rate_std": finite_or_none(self.rate_std),
            "drift": finite_or_none(self.drift),
            "drift_std": finite_or_none(self.drift_std),
            "links": int(self.links),
            "track_residual_px": finite_or_none(self.track_residual_px),
            "frame_scatter": finite_or_none(self.frame_scatter),
        }

    @classmethod
    def from_json(cls, v: Any) -> VideoClockReport:
        """Inverse of `to_json`; malformed input raises KeyError, TypeError or ValueError."""
        return cls(
            name=str(v["video"]),
            time_source=TimeSource(v["time_source"]),
            method=str(v["method"]),
            identified=bool(v["identified"]),
            offset=float_or_nan(v["offset"]),
            offset_std=float_or_nan(v["offset_std"]),
            rate=float_or_nan(v["rate"]),
            rate_std=float_or_nan(v["rate_std"]),
            drift=float_or_nan(v["drift"]),
            drift_std=float_or_nan(v["drift_std"]),
            links=int(v.get("links", 0)),
            track_residual_px=float_or_nan(v.get("track_residual_px")),
            frame_scatter=float_or_nan(v.get("frame_scatter")),
        )


@dataclass(kw_only=True)
class Clocks:
    """Every video's recovered clock and every frame's global time (sequencing.json `clocks`)."""

    model: ClockModel
    reference: str
    videos: list[VideoClockReport]
    frame_videos: list[str]  # (F,)
    frames: np.ndarray  # (F,) frame numbers
    own_time: np.ndarray  # (F,) s
    global_time: np.ndarray  # (F,) s, NaN for frames of unidentified videos
    global_std: np.ndarray  # (F,) s
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    # The same clocks with W's links' clock for the videos whose tracks' clock was kept against them (None: they
    # agreed): the second hypothesis the refinement measures (reconstruct/temporal.py); not written anywhere.
    links_alternative: Clocks | None = None

    def video(self, name: str) -> VideoClockReport:
        for clock in self.videos:
            if clock.name == name:
                return clock
        raise KeyError(name)

    def refit(self, video_index: np.ndarray, times: np.ndarray) -> Clocks:
        """These clocks with each identified video's offset/rate(/drift) refitted to `times (F,)` and those times as
        the per-frame global times. `times` must be in the clocks' gauge (the reference video's global time = its
        own time). The uncertainties are widened by the move: two estimates of one clock (the tracks' or the links',
        and the trajectories' polish or free times) that differ by more than the first one's standard deviation show
        it too small (measured on real rigs: docs/clocks.md); `estimate_std` keeps the first."""
        degree = self.model.refit_degree
        times = np.asarray(times, dtype=float)
        for v, clock in enumerate(self.videos):
            own = video_index == v
            if own.sum() <= degree or not clock.identified:
                continue
            before = clock.offset
            clock.refit(self.own_time[own], times[own], self.model)
            if not math.isfinite(clock.estimate_std):
                clock.estimate_std = clock.offset_std
            if math.isfinite(before) and math.isfinite(clock.offset_std):
                clock.offset_std = math.hypot(clock.offset_std, clock.offset - before)
        moved = np.abs(times - self.global_time)
        self.global_std = np.where(np.isfinite(moved), np.hypot(self.global_std, np.nan_to_num(moved)), self.global_std)
        self.global_time = times.copy()
        return self

    def to_json(self) -> dict[str, Any]:
        """The `clocks` value of sequencing.json (JSON types only; NaN -> null)."""
        return {
            "model": self.model.value,
            "unit": "s",
            "reference": self.reference,
            "videos": [c.to_json() for c in self.videos],
            "frames": [
                {
                    "video": v,
                    "frame": int(f),
                    "own_time": finite_or_none(o),
                    "time": finite_or_none(g),
                    "time_std": finite_or_none(s),
                }
                for v, f, o, g, s in zip(
                    self.frame_videos, self.frames, self.own_time, self.global_time, self.global_std, strict=True
                )
            ],
            "warnings": list(self.warnings),
            "diagnostics": _plain(self.diagnostics),
        }

    @classmethod
    def from_json(cls, document: Any, path: str | Path | None = None) -> Clocks:
        """Inverse of `to_json`; malformed input raises InputError naming `path`."""
        try:
            videos = [VideoClockReport.from_json(v) for v in document["videos"]]
            entries = document["frames"]
            return cls(
                model=ClockModel(document["model"]),
                reference=str(document["reference"]),
                videos=videos,
                frame_videos=[str(e["video"]) for e in entries],
                frames=np.array([int(e["frame"]) for e in entries], dtype=np.int64),
                own_time=np.array([float_or_nan(e["own_time"]) for e in entries]),
                global_time=np.array([float_or_nan(e["time"]) for e in entries]),
                global_std=np.array([float_or_nan(e["time_std"]) for e in entries]),
                warnings=[str(w) for w in document.get("warnings", [])],
                diagnostics=dict(document.get("diagnostics", {})),
            )
        except (KeyError, TypeError, ValueError, OverflowError, RecursionError) as error:
            raise InputError(
                path,
                f"invalid 'clocks' entry: {repr(error)[:200]}",
                fix="rewrite it with `dynrecon solve`, or remove the key",
            ) from None


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
