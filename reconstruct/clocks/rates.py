"""Do the frame rates given for videos without decoder times hold? (`register --fps`'s names, a lab calibration
imported with `--fps`: frames at frame / fps, a rate somebody typed, not one a decoder measured.)

A lab camera runs at its rate; a phone's true rate may miss its nominal one by a little, which over minutes moves
its frames by many periods. The given rate is kept (offset-only clocks, as for decoder times) unless the tracks
say otherwise: the clocks are searched once with a free rate per video, and a video whose rate differs from the
given one by more than `SIGMAS` standard deviations and the search's rate prior, and by enough to move its last frame
`DRIFT_PERIODS` frame periods, makes the solve fit every video's rate (affine clocks). A free rate where the given
one holds costs accuracy: it trades offset against rate on a short capture.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from reconstruct.clocks.estimate import ClockOptions, choose_reference
from reconstruct.clocks.model import ClockModel, TimeSource, frame_periods, own_times
from reconstruct.clocks.search import search_clocks
from reconstruct.solver.problem import Problem

log = logging.getLogger(__name__)

# A rate differs from the given one beyond this many of its standard deviations and beyond the search's own rate
# prior (`SearchOptions.rate_prior`, a quartz clock's error): the standard deviations undershoot the scatter of
# rates fitted to cameras that run at their given rate (docs/clocks.md, "Given frame rates").
SIGMAS = 3.0
DRIFT_PERIODS = 0.25  # ... and moves the video's frames by at least this share of a frame over its span

__all__ = ["RateCheck", "check_given_rates"]


@dataclass(kw_only=True)
class RateCheck:
    """The clock model the test chose, and per video given a rate: its fitted rate over the given one, the
    rate's standard deviation, the drift over its span in frame periods, and whether that differs."""

    model: ClockModel
    videos: list[dict[str, Any]] = field(default_factory=list)

    @property
    def reason(self) -> str:
        off = [v for v in self.videos if v["differs"]]
        if off:
            worst = max(off, key=lambda v: abs(v["drift_periods"]))
            return (
                f"{len(off)} video(s) run off the frame rate given (first: {worst['video']!r}, rate"
                f" {worst['rate']:.5f} +- {worst['rate_std']:.1g}: {worst['drift_periods']:+.2f} frames over its span):"
                " each video's rate is fitted"
            )
        return "the frame rates given hold (no video's rate differs from its given one): offset-only clocks"

    def to_json(self) -> dict[str, Any]:
        return {"model": self.model.value, "reason": self.reason, "videos": self.videos}


def check_given_rates(problem: Problem, options: ClockOptions) -> RateCheck | None:
    """The clock model for videos whose times are a given rate's (`options.fps`), tested against the tracks;
    None where no video has a given rate or some video has no rate at all (its own rate is fitted anyway)."""
    own, sources = own_times(problem, options.fps)
    if TimeSource.FPS not in sources or TimeSource.NOMINAL in sources:
        return None
    N = len(problem.video_names)
    ref = choose_reference(problem, sources, options.reference)
    search = search_clocks(
        problem,
        own,
        ref,
        ClockModel.AFFINE,
        sources,
        options.track_search,
        movable_reference=options.reference is None,
    )
    params = search.params
    floor = options.track_search.rate_prior
    periods = frame_periods(own, problem.video_index, N)
    videos = []
    for v, name in enumerate(problem.video_names):
        if v == search.reference or not params.identified[v] or sources[v] is not TimeSource.FPS:
            continue
        rate, variance = float(params.coef[v, 1]), float(params.cov[v, 1, 1])
        std = math.sqrt(variance) if math.isfinite(variance) and variance > 0 else math.inf
        span = float(np.ptp(own[problem.video_index == v]))
        drift = (rate - 1.0) * span / float(periods[v]) if np.isfinite(periods[v]) and periods[v] > 0 else 0.0
        differs = bool(abs(rate - 1.0) > max(SIGMAS * std, floor) and abs(drift) > DRIFT_PERIODS)
        rate_std = std if math.isfinite(std) else None
        videos.append({"video": name, "rate": rate, "rate_std": rate_std, "drift_periods": drift, "differs": differs})
    model = ClockModel.AFFINE if any(v["differs"] for v in videos) else ClockModel.OFFSET
    return RateCheck(model=model, videos=videos)
