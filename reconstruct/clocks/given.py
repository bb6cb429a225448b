"""Clock offsets the solve did not find itself (registration's, or declared synchronized in cameras.json), tested
against the tracks before they are used: each pair of videos' own track search (`search.search_pair`, rate 1) may
refute them. A pair refutes the given offsets when its search is clearly distinct (runner-up at least REFUTE_RATIO x
its best cost), its best lies outside the given offset's basin (more than the search's DISTINCT_STEPS grid steps
away) and the given relative offset costs at least REFUTE_RATIO x that best. Refuting asks for more than the
search's own MIN_DISTINCTNESS: with cameras a degree off, a pair's search can prefer a wrong offset mildly
(docs/refinement.md, "Few points on cameras.json's offsets"). Pairs whose search is not that distinct, or that do
not overlap at the given offset, say nothing; within the basin the clock polish settles the offset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynrecon.jsonvalues import finite_or_none
from reconstruct.clocks.model import TimeSource, frame_periods
from reconstruct.clocks.search import (
    COARSE_STEP_PERIODS,
    DISTINCT_STEPS,
    SearchOptions,
    pair_cost,
    search_pair,
    video_tracks,
)
from reconstruct.solver.problem import Problem

REFUTE_RATIO = 2.0  # the pair's runner-up and the given offset's cost over its best, both at least this


@dataclass(kw_only=True)
class PairVerdict:
    """One pair's search against the given offsets: own_u = own_v + given (s) on the given clocks."""

    v: str
    u: str
    given_s: float
    best_s: float
    best_cost: float  # px^2, the pair's mean truncated squared gap at its best offset
    given_cost: float  # ... at the given offset (inf: the tracks do not overlap there)
    distinctness: float  # runner-up / best cost of the pair's own search
    basin_s: float  # the search's distinct distance: offsets closer to its best are the same minimum

    @property
    def refutes(self) -> bool:
        return (
            self.distinctness >= REFUTE_RATIO
            and abs(self.given_s - self.best_s) > self.basin_s
            and math.isfinite(self.given_cost)
            and self.given_cost >= REFUTE_RATIO * self.best_cost
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "videos": [self.v, self.u],
            "given_s": finite_or_none(self.given_s),
            "best_s": finite_or_none(self.best_s),
            "cost_px2": {"best": finite_or_none(self.best_cost), "given": finite_or_none(self.given_cost)},
            "distinctness": finite_or_none(self.distinctness),
            "basin_s": finite_or_none(self.basin_s),
            "refutes": self.refutes,
        }


def corroborated(verdict: PairVerdict, verdicts: list[PairVerdict]) -> bool:
    """Whether another pair of videos shares `verdict`'s evidence against the given offsets. Its best says one of
    its two videos is off by d = best - given; another pair with that video agrees when its own best lies within
    its basin of its given offset moved by that d (either video may be the one off). True where no other pair
    shares a video (nothing to ask), so that two videos keep the single pair's word."""
    d = verdict.best_s - verdict.given_s
    others = [o for o in verdicts if o is not verdict and {o.v, o.u} & {verdict.v, verdict.u}]
    if not others:
        return True
    for other in others:
        # given = offset_v - offset_u: moving video u's offset by -d adds d where u is second and subtracts it where
        # u is first; moving video v's by +d does the same for v.
        for moved, shift in ((verdict.u, d), (verdict.v, -d)):
            if moved not in (other.v, other.u):
                continue
            expected = other.given_s + (shift if other.u == moved else -shift)
            if abs(other.best_s - expected) <= other.basin_s:
                return True
    return False


def pair_verdicts(problem: Problem, own: np.ndarray, offsets: np.ndarray, options: SearchOptions) -> list[PairVerdict]:
    """Every pair's verdict on the offsets (N,) s (global = own + offset) of the videos' own times `own (F,)`."""
    N = len(problem.video_names)
    counts = problem.observed.sum(axis=0)
    points = np.argsort(-counts, kind="stable")[: options.max_points]
    points = points[counts[points] > 0]
    tracks = video_tracks(problem, own, points)  # as the search reads them
    periods = frame_periods(own, problem.video_index, N)
    sources = [TimeSource.DECODER] * N  # the given offsets keep each video's own rate
    verdicts = []
    for v in range(N):
        for u in range(v + 1, N):
            best = search_pair(tracks, v, u, options, periods, sources)
            if best is None:
                continue
            given = float(offsets[v] - offsets[u])  # own_u = own_v + offset_v - offset_u
            cost = pair_cost(tracks, v, u, given, 1.0, options, best.count)  # judged on the best's samples
            verdicts.append(
                PairVerdict(
                    v=problem.video_names[v],
                    u=problem.video_names[u],
                    given_s=given,
                    best_s=best.alpha,
                    best_cost=best.cost,
                    given_cost=float(cost),
                    distinctness=best.distinctness,
                    basin_s=DISTINCT_STEPS * COARSE_STEP_PERIODS * float(np.nanmax([periods[v], periods[u]])),
                )
            )
    return verdicts
