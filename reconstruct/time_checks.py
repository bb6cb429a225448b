"""Time hypotheses are checked before they are trusted (docs/refinement.md, "Never worse").

Before the clock model is used: every video clocked, W's links agree with it to within a frame period where frames
have no decoder times (the model then assumes even spacing), and the track search found a distinct best offset.
After a refinement: it fits its rays about as well as trajectories on free per-frame times do (the clock model
costs no residual), and it moves the seed solve's points no further than the noise it removes. Without a clock
model, the polished frame order is used only when its even times fit about as well as the spectral order's
(`order_fit`). Every check has a name, a number and its limit, in report.json `temporal.checks`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from reconstruct.clocks.given import PairVerdict, corroborated, pair_verdicts
from reconstruct.clocks.model import Clocks, TimeSource, frame_periods
from reconstruct.clocks.search import SearchOptions
from reconstruct.free_times import FreeTimes, refine_free_times, reprojection_px
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays
from reconstruct.trajectory import RefineOptions, RefineResult

LINK_MAX_PERIODS = 1.0  # W links' robust time residual, in the fastest video's frame periods
MIN_DISTINCTNESS = 1.05  # the track search's runner-up cost over its best
FIT_PX = 0.5  # a refinement whose median reprojection residual is below this fits its rays: nothing to compare
CLOCK_COST_FACTOR = 1.25  # the clock refinement's residual may exceed the free-time one by this factor...
CLOCK_COST_PX = 0.25  # ... plus this
SEED_SHIFT_FACTOR = 3.0  # a refinement may move the seed's points by this x its median residual...
SEED_SHIFT_PX = 1.0  # ... plus this
MAX_FAR_SHARE = 0.25  # beyond this share of points moved further, the refinement disagrees with the seed


class TimePath(enum.Enum):
    CLOCKS = "clocks"  # trajectories on the clock model's times
    FREE_TIMES = "free_times"  # trajectories on a time per frame, without a clock model
    SEED = "seed"  # the self-expressive solve's points, not refined


@dataclass(frozen=True)
class Check:
    name: str
    value: float
    limit: float
    passed: bool
    meaning: str  # what the number is, for the log and the report

    def sentence(self) -> str:
        relation = ">=" if self.name == "track_distinctness" else "<="
        return f"check {self.name!r} failed: {self.meaning} {self.value:.3g} (limit {relation} {self.limit:.3g})"

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Check:
        """The check `to_json` wrote (None: a value or limit that was not finite)."""
        value, limit = data.get("value"), data.get("limit")
        return cls(
            name=str(data["name"]),
            value=math.nan if value is None else float(value),
            limit=math.inf if limit is None else float(limit),
            passed=bool(data["passed"]),
            meaning=str(data["meaning"]),
        )

    def to_json(self) -> dict[str, Any]:
        value = self.value if math.isfinite(self.value) else None
        limit = self.limit if math.isfinite(self.limit) else None
        return {"name": self.name, "value": value, "limit": limit, "passed": self.passed, "meaning": self.meaning}


def spacing_assumed(clocks: Clocks) -> bool:
    """Whether some video has no decoder times, so that its clock assumes evenly spaced frames (W's links test it)."""
    return any(c.time_source is not TimeSource.DECODER for c in clocks.videos)


def rate_unknown(clocks: Clocks) -> bool:
    """Whether some video has neither decoder times nor a given frame rate: its clock's rate is the model's guess,
    which trajectories on free per-frame times judge. A given rate is judged as decoder times are: on real rigs free
    times absorb calibration and tracking errors that no clock explains (docs/clocks.md, "Given frame rates")."""
    return any(c.time_source is TimeSource.NOMINAL for c in clocks.videos)


def clock_checks(problem: Problem, clocks: Clocks, min_distinctness: float = MIN_DISTINCTNESS) -> list[Check]:
    """The clock model tested against the data before it is used (`min_distinctness`: the track search's
    runner-up margin it needs)."""
    identified = sum(c.identified for c in clocks.videos)
    checks = [
        Check(
            name="identified",
            value=float(len(clocks.videos) - identified),
            limit=0.0,
            passed=identified == len(clocks.videos),
            meaning="videos whose clock could not be recovered",
        )
    ]
    periods = frame_periods(clocks.own_time, problem.video_index, len(problem.video_names))
    scale = clocks.diagnostics.get("link_scale_s")
    # Without decoder times the clock model assumes evenly spaced frames, which W's links test. With them the
    # spacing is measured, and links may join other cycles of a periodic motion: the refinement's fit decides.
    assumed = spacing_assumed(clocks)
    if assumed and isinstance(scale, float) and math.isfinite(scale) and np.isfinite(periods).any():
        ratio = scale / float(np.nanmin(periods))
        checks.append(
            Check(
                name="link_residual",
                value=ratio,
                limit=LINK_MAX_PERIODS,
                passed=ratio <= LINK_MAX_PERIODS,
                meaning="W links' robust time residual in frame periods",
            )
        )
    distinct = clocks.diagnostics.get("track_distinctness")
    if isinstance(distinct, float) and math.isfinite(distinct):
        checks.append(
            Check(
                name="track_distinctness",
                value=distinct,
                limit=min_distinctness,
                passed=distinct >= min_distinctness,
                meaning="track search's runner-up cost over its best (median over video pairs)",
            )
        )
    return checks


class RefinementJudge:
    """Measures refinements of one solve on equal terms; the free-time refinement is computed once, when needed."""

    def __init__(self, problem: Problem, result: SolveResult, options: RefineOptions) -> None:
        self.problem = problem
        self.result = result
        self.options = options
        self.rays = viewing_rays(problem)
        self._free: FreeTimes | None = None
        self._free_px = math.nan  # median residual on free per-frame times: clock_fit's yardstick
        self._order_check: Check | None = None
        self._on_order = False  # whether free() holds the polished order's result

    def residual(self, points: np.ndarray) -> float:
        """Median reprojection residual (px) of `points (F, P, 3)` over the observations."""
        values = reprojection_px(self.problem, points, self.rays)
        finite = values[np.isfinite(values)]
        return float(np.median(finite)) if len(finite) else math.nan

    def free(self) -> FreeTimes:
        """The refinement without a clock model: from the polished frame order when its even times cost no residual
        against the spectral order's (`order_fit`), else from the spectral order (retimed free times)."""
        if self._free is None:
            free = refine_free_times(self.problem, self.result.points, self.result.W.to_csc(), self.options, self.rays)
            self._free_px = self.residual(free.result.points)
            self._order_check = self._order_fit(free)
            if self._order_check is not None and self._order_check.passed and free.ordered is not None:
                assert free.ordered_times is not None
                free = dataclasses.replace(free, times=free.ordered_times, result=free.ordered)
                self._on_order = True
            self._free = free
        return self._free

    def _order_fit(self, free: FreeTimes) -> Check | None:
        if free.on_ranks is None:
            return None
        residual = self.residual(free.on_ranks.points)
        # Against the spectral order's even times, the start it replaces (same freedom): free per-frame times can
        # pass a spline through noisy rays, which makes their residual no yardstick there.
        spectral = free.spectral_px
        limit = max(FIT_PX, CLOCK_COST_FACTOR * spectral + CLOCK_COST_PX)
        return Check(
            name="order_fit",
            value=residual,
            limit=limit,
            passed=residual <= limit,
            meaning=(
                f"median reprojection residual (px) on the polished frame order's even times, against"
                f" {spectral:.3g} px on the spectral order's"
            ),
        )

    def free_report(self) -> dict[str, Any]:
        """Which times the refinement without a clock model used, and why (for report.json `temporal`)."""
        free = self.free()
        check = self._order_check
        return {
            "free_times_source": "order" if self._on_order else "retimed",
            "free_times_order_fit": check.to_json() if check is not None else None,
            "free_times_order_path": free.order_path,
        }

    def clock_fit(self, refined: RefineResult, assumed: bool = True) -> list[Check]:
        """The clock model costs no residual: its trajectories fit the rays to FIT_PX, or about as well as
        trajectories on free per-frame times. Only where the model assumes the frames' spacing (`assumed`): with
        decoder times, free times also absorb calibration and tracking errors that no clock explains, so the
        comparison would refuse good clocks on real rigs; the residual is then reported, not judged (so with a
        given frame rate: `rate_unknown`)."""
        residual = self.residual(refined.points)
        if not assumed:
            return [
                Check(
                    name="clock_fit",
                    value=residual,
                    limit=math.inf,
                    passed=True,
                    meaning=(
                        "median reprojection residual (px) on the clocks (decoder times or given rates: reported,"
                        " not judged)"
                    ),
                )
            ]
        if residual <= FIT_PX:
            return [
                Check(
                    name="clock_fit",
                    value=residual,
                    limit=FIT_PX,
                    passed=True,
                    meaning="median reprojection residual (px) of the trajectories on the clocks",
                )
            ]
        self.free()
        free = self._free_px
        limit = CLOCK_COST_FACTOR * free + CLOCK_COST_PX
        return [
            Check(
                name="clock_fit",
                value=residual,
                limit=limit,
                passed=residual <= limit,
                meaning=f"median reprojection residual (px) on the clocks, against {free:.3g} px on free times",
            )
        ]

    def seed_agreement(self, refined: RefineResult, label: str) -> list[Check]:
        """The refinement moves few of the seed's points (reprojected, px) further than the noise it removes."""
        residual = self.residual(refined.points)
        far = self._far(refined)
        counted = np.isfinite(self.result.points[..., 0])
        share = float(far[counted].mean()) if counted.any() else 1.0
        meaning = (
            f"share of the seed's points moved by more than {SEED_SHIFT_FACTOR:g} x the residual ({residual:.3g} px)"
            f" + {SEED_SHIFT_PX:g} px"
        )
        # order_fit is a check of the path that used the order (when it failed: in free_report only)
        used_order = self._on_order and self._order_check is not None and refined is self.free().result
        order = [self._order_check] if used_order and self._order_check is not None else []
        shift = Check(
            name=f"{label}_seed_shift", value=share, limit=MAX_FAR_SHARE, passed=share <= MAX_FAR_SHARE, meaning=meaning
        )
        return [*order, shift]  # the seed shift last: temporal's warning names it

    def _far(self, refined: RefineResult) -> np.ndarray:
        """(F, P) bool: points the refinement moved from the seed's beyond the seed-agreement limit."""
        limit = SEED_SHIFT_FACTOR * self.residual(refined.points) + SEED_SHIFT_PX
        return ~(self.shifts_px(refined.points) <= limit) & np.isfinite(self.result.points[..., 0])

    def _misfit(self, refined: RefineResult) -> np.ndarray:
        """(F, P) bool: observations whose residual exceeds the seed-agreement limit; an unobserved point takes its
        frame's median residual."""
        values = reprojection_px(self.problem, refined.points, self.rays)
        limit = SEED_SHIFT_FACTOR * self.residual(refined.points) + SEED_SHIFT_PX
        frame = np.full(len(values), np.inf)
        seen = np.isfinite(values).any(axis=1)
        frame[seen] = np.nanmedian(values[seen], axis=1)
        filled = np.where(np.isfinite(values), values, frame[:, None])
        return ~(filled <= limit)

    def shifts_px(self, points: np.ndarray) -> np.ndarray:
        """(F, P) distance of `points` from the seed's, in pixels at the seed point's distance from the camera."""
        problem, seed = self.problem, self.result.points
        centers = problem.centers
        depth = np.linalg.norm(seed - centers[:, None, :], axis=-1)
        return np.linalg.norm(points - seed, axis=-1) * problem.K[:, 0, 0][:, None] / np.maximum(depth, 1e-9)

    def keep_seed_where_far(self, refined: RefineResult) -> tuple[np.ndarray, float]:
        """The refined points, except where one moved the seed's beyond the seed-agreement limit: there the seed's
        point is kept (a frame whose free time went wrong fits its rays at a wrong depth). Returns the points
        (F, P, 3) and the share of points kept from the seed."""
        far = self._far(refined)
        if self._on_order and refined is self.free().result:
            # from a checked order a far point that fits its ray is kept: corrected seed points are the ones that move
            far &= self._misfit(refined)
        points = np.where(far[..., None], self.result.points, refined.points)
        counted = np.isfinite(self.result.points[..., 0])
        return points, float(far[counted].mean()) if counted.any() else 0.0


def given_offsets_check(
    problem: Problem, clocks: Clocks, options: SearchOptions, *, corroboration: bool = False
) -> tuple[Check, list[PairVerdict]]:
    """`given_offsets`: no pair of videos refutes the offsets of `clocks` (each video's global = own + offset).
    `corroboration`: a refuting pair counts only where another pair with one of its videos agrees
    (`clocks.given.corroborated`); for callers that weigh the offsets by a measured criterion next, so that one
    pair whose neighbours contradict it does not decide alone."""
    offsets = np.array([video.offset for video in clocks.videos])
    verdicts = pair_verdicts(problem, clocks.own_time, offsets, options)
    refuting = [v for v in verdicts if v.refutes]
    aside = [v for v in refuting if corroboration and not corroborated(v, verdicts)]
    refuting = [v for v in refuting if v not in aside]
    first = (
        f"{refuting[0].v}-{refuting[0].u} at {refuting[0].best_s:+.3f} s, not {refuting[0].given_s:+.3f}"
        if refuting
        else "none"
    )
    note = ""
    if aside:
        note = f"; {len(aside)} set aside, no other pair agreeing (first: {aside[0].v}-{aside[0].u} at "
        note += f"{aside[0].best_s:+.3f} s)"
    check = Check(
        name="given_offsets",
        value=float(len(refuting)),
        limit=0.0,
        passed=not refuting,
        meaning=f"pairs of videos whose tracks clearly prefer another offset (first: {first}{note})",
    )
    return check, verdicts
