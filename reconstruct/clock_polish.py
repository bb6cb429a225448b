"""The clock polish (docs/refinement.md): per-video offset (and rate) corrections of the global times that minimize
the trajectory refinement's own cost, found by coordinate descent with the smoothness and robust weights of a first
refinement held fixed (`clocks.model.ClockCorrection`); then the refinement again on the polished times.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded

from reconstruct import trajectory
from reconstruct.block_inverse import BANDS
from reconstruct.clocks.model import ClockCorrection
from reconstruct.solver.problem import Problem, most_observed
from reconstruct.solver.rays import camera_normalization, viewing_rays
from reconstruct.spline_system import (
    LOWER,
    LOWER_DIAGONAL,
    MERGE_FRACTION,
    PRIOR_DIAGONALS,
    prior_bands,
    prior_value,
    sum_at_slots,
    time_nodes,
    zero_row,
)
from reconstruct.trajectory import RefineOptions, RefineResult, refine

log = logging.getLogger(__name__)

POLISH_ROUNDS = 2  # refine (choosing the smoothness), then search the clocks; repeated
POLISH_SWEEPS = 4  # coordinate-descent sweeps over the videos per round
POLISH_REACH_PERIODS = 1.0  # each sweep searches a video's offset within +- this many of its frame periods
POLISH_TOLERANCE = 0.005  # the golden-section search stops at this share of its reach
POLISH_STOP = 1e-6  # sweeps stop when one lowers the cost by less than this share
# Beyond this many point-frames the polish's cost uses the most observed points up to it (at least
# POLISH_MIN_POINTS): every point sees the same clocks, and each cost evaluation solves every point over every
# instant, dozens of times per polish.
POLISH_SIZE = 200_000
POLISH_MIN_POINTS = 4


@dataclass(kw_only=True)
class ClockRefineResult:
    times: np.ndarray  # (F,) adjusted global times, s
    correction: ClockCorrection  # from the input times to `times` (the reference's is 0)
    cost: list[float]  # trajectory cost after each sweep (px^2)
    result: RefineResult  # the refinement at the adjusted times
    at_input: RefineResult | None = None  # the refinement at the input times (what a rejected polish falls back to)


def refine_with_clocks(
    problem: Problem,
    points: np.ndarray,
    times: np.ndarray,
    options: RefineOptions | None = None,
    *,
    reference: int | None = None,
    rates: bool = True,
) -> ClockRefineResult:
    """`refine`, then per-video time offsets (and, with `rates`, rates) that minimize the refinement's own cost,
    then `refine` again; POLISH_ROUNDS times (each round re-chooses the smoothness: wrong times make GCV smooth
    more, which flattens the cost the clocks are searched on). Video `reference` keeps its clock (default: the one
    with most frames): the cost does not see a global affine change of time."""
    options = options or RefineOptions()
    times = np.asarray(times, dtype=float)
    original = times
    result = _clock_round(problem, points, times, options, reference, rates)
    at_input = result.at_input
    history = list(result.cost)
    for _ in range(POLISH_ROUNDS - 1):
        if np.array_equal(result.times, times):
            break  # no clock moved: another round would repeat this one exactly
        times = result.times
        # the round's own first refinement would repeat the last one (same inputs): start from it
        result = _clock_round(problem, points, result.times, options, reference, rates, result.result)
        history.extend(result.cost)
    # Corrections relative to the input times (the rounds compose affine maps per video).
    correction = ClockCorrection.fit(original, result.times, problem.video_index, len(problem.video_names))
    return ClockRefineResult(
        times=result.times, correction=correction, cost=history, result=result.result, at_input=at_input
    )


def _clock_round(
    problem: Problem,
    points: np.ndarray,
    times: np.ndarray,
    options: RefineOptions,
    reference: int | None,
    rates: bool,
    first: RefineResult | None = None,
) -> ClockRefineResult:
    """One round of refine_with_clocks; `first`: the refinement at `times`, when an earlier round computed it.

    Estimated clocks can be off by a fraction of a frame, which folds the trajectory into a zig-zag the prior pays
    for. With the smoothness and robust weights of a first refinement held fixed, the cost (weighted ray distances
    + smoothness) is a function of the clocks alone; each video's offset (then rate) is found by golden-section
    search in turn (coordinate descent).
    """
    first = first if first is not None else refine(problem, points, times, options)
    N = len(problem.video_names)
    counts = np.bincount(problem.video_index, minlength=N)
    if reference is None:
        reference = int(np.argmax(counts))
    middle = np.array([np.median(times[problem.video_index == v]) if counts[v] else 0.0 for v in range(N)])
    correction = ClockCorrection.none(middle)
    if not np.isfinite(first.smoothness).any():  # no point refined (times with every video apart): no cost to search
        return ClockRefineResult(times=times, correction=correction, cost=[], result=first, at_input=first)
    with trajectory.worker_pool() as pool:
        cost = _PolishCost(problem, first, times, pool)
        history = _coordinate_descent(cost, times, problem.video_index, correction, rates)
    adjusted, correction = correction.in_gauge_of(reference, times, problem.video_index)
    log.info(
        "clock offsets (ms): %s; rates (ms/s): %s; trajectory cost %.4g -> %.4g",
        ", ".join(f"{1000 * o:+.2f}" for o in correction.offset),
        ", ".join(f"{1000 * r:+.2f}" for r in correction.rate),
        history[0],
        history[-1],
    )
    # a polish that moved no clock leaves the times bitwise as they were: the first refinement is the final one
    final = first if np.array_equal(adjusted, times) else refine(problem, points, adjusted, options)
    return ClockRefineResult(times=adjusted, correction=correction, cost=history, result=final, at_input=first)


class _PolishCost:
    """The refinement's cost (px^2) at candidate frame times, one banded solve for all refined points; held fixed:
    the smoothness and robust weights of a first refinement, and each observation's px scale from its positions
    (time shifts of a fraction of a frame barely move the depths). The points are independent: with a `pool`,
    each worker solves a run of them (`_PolishPart`), and only the final sums are taken over all."""

    def __init__(
        self, problem: Problem, first: RefineResult, times: np.ndarray, pool: ThreadPoolExecutor | None = None
    ):
        self.pool = pool
        normalization = camera_normalization(problem.centers, problem.video_index)
        centers = normalization.apply(problem.centers)
        rays = viewing_rays(problem)
        focal = np.sqrt(problem.K[:, 0, 0] * problem.K[:, 1, 1])
        self.tau = time_nodes(times).tau
        self.span = float(np.ptp(times))
        refined = _polish_points(problem.observed, np.isfinite(first.smoothness))
        observed = problem.observed & refined[None, :]
        frame, point = np.nonzero(observed)  # every observation of a refined point
        keep = np.flatnonzero(refined)
        column = np.searchsorted(keep, point)  # the observation's point among the refined ones
        positions = normalization.apply(first.points)
        depth = np.einsum("mi,mi->m", positions[frame, point] - centers[frame], rays[frame, point])
        s2 = (focal[frame] / np.maximum(depth, 1e-9)) ** 2
        self.weight = np.nan_to_num(first.weights[frame, point]) * s2
        mean_s2 = np.array([np.mean(np.sqrt(s2[column == k])) ** 2 for k in range(len(keep))])
        self.strength = first.smoothness[keep] * mean_s2  # (P',)
        self.num_observations = len(frame)
        workers = trajectory.WORKERS if pool is not None else 1
        bounds = [len(keep) * w // workers for w in range(workers + 1)]
        self.parts = [
            _PolishPart(
                observations=np.flatnonzero((column >= low) & (column < high)),
                first=low,
                frame=frame,
                column=column,
                rays=rays[frame, point],
                centers=centers[frame],
                weight=self.weight,
                strength=self.strength[low:high],
                known_positions=np.nan_to_num(positions[:, keep[low:high]]),
            )
            for low, high in itertools.pairwise(bounds)
            if high > low
        ]

    def __call__(self, candidate: np.ndarray) -> float:
        # Time unit proportional to the span: the cost is then invariant to a global affine change of time (the
        # gauge), so every video, the reference included, can move alone.
        nodes = time_nodes(candidate, MERGE_FRACTION, self.tau * float(np.ptp(candidate)) / self.span)
        prior = prior_bands(nodes)
        frames_at = np.bincount(nodes.node_of_frame, minlength=len(nodes.times))

        def run(part: _PolishPart) -> tuple[np.ndarray, np.ndarray]:
            return part.evaluate(nodes.node_of_frame, frames_at, prior)

        solved = self.pool.map(run, self.parts) if self.pool is not None else map(run, self.parts)
        squared = np.empty(self.num_observations)
        prior_values = []
        try:
            for part, (distance2, value) in zip(self.parts, solved, strict=True):
                squared[part.observations] = distance2
                prior_values.append(value)
        except LinAlgError:
            # times that leave some point's system numerically singular are no candidate: the search moves on, and
            # a polish whose own start is one is rejected (its cost is not finite)
            return math.inf
        total = float(np.sum(self.weight * squared))
        return total + float(np.sum(self.strength * np.concatenate(prior_values)))


class _PolishPart:
    """A run of the polish cost's points, `first` on: their observations (indices among all, in their order) and
    what their systems need, each observation with a zero row for `sum_at_slots`."""

    def __init__(
        self,
        *,
        observations: np.ndarray,
        first: int,
        frame: np.ndarray,
        column: np.ndarray,
        rays: np.ndarray,
        centers: np.ndarray,
        weight: np.ndarray,
        strength: np.ndarray,
        known_positions: np.ndarray,
    ):
        self.observations = observations
        self.frame = frame[observations]
        self.column = column[observations] - first  # the observation's point within the part
        self.strength = strength  # (K,)
        self.rays, self.centers = rays[observations], centers[observations]
        projector = np.eye(3)[None] - self.rays[:, :, None] * self.rays[:, None, :]
        blocks = weight[observations, None, None] * projector
        # each block's lower triangle (m + 1, 6), all the systems need, and right-hand side (m + 1, 3)
        self.lower = zero_row(np.stack([blocks[:, row, col] for row, col in LOWER], axis=1))
        self.rhs = zero_row(np.einsum("mij,mj->mi", blocks, self.centers))
        self.known_positions = zero_row(known_positions)  # (F + 1, K, 3)

    def evaluate(
        self, node_of_frame: np.ndarray, frames_at: np.ndarray, prior: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The part's squared ray distances (m,), unweighted, and prior values (K,) at the solved positions, for the
        instants `node_of_frame (F,)` holding `frames_at (n,)` frames each."""
        K, n = len(self.strength), len(frames_at)
        node = node_of_frame[self.frame]
        slot = self.column * n + node
        alone = frames_at[node] == 1  # an instant of one frame holds one observation of each point
        lower = sum_at_slots(slot, self.lower, K * n, alone).reshape(K, n, 6)
        rhs = sum_at_slots(slot, self.rhs, K * n, alone).reshape(K, n, 3)
        d0, d1, d2 = LOWER_DIAGONAL
        eps = 1e-9 * np.maximum(np.mean(lower[..., d0] + lower[..., d1] + lower[..., d2], axis=1), 1e-300)
        lower[..., LOWER_DIAGONAL] += eps[:, None, None]  # + eps I (the off-diagonal entries' + 0 changes nothing)
        # mean position per instant (the tiny eps pull's target)
        anchor = sum_at_slots(node_of_frame, self.known_positions, n, frames_at[node_of_frame] == 1)
        anchor /= np.maximum(frames_at, 1)[:, None, None]
        rhs += eps[:, None, None] * anchor.transpose(1, 0, 2)
        # Points are independent: their systems side by side form one banded matrix (no band crosses a seam, and
        # LAPACK's banded Cholesky, unblocked for so few bands, and solves work column by column: each point's
        # numbers are its own, whichever points share the call).
        system = np.zeros((BANDS, K, 3 * n))  # (BANDS, K, 3n); the prior's other bands are zero
        for d in PRIOR_DIAGONALS:
            np.multiply(self.strength[:, None], prior[d], out=system[d])
        columns = system.reshape(BANDS, K, n, 3)  # a view: column 3i + col of point k is [:, k, i, col]
        for entry, (row, col) in enumerate(LOWER):
            columns[row - col, :, :, col] += lower[:, :, entry]
        # finite by construction: LAPACK's own checks suffice
        factor = cholesky_banded(system.reshape(BANDS, -1), lower=True, check_finite=False)
        solved = cho_solve_banded((factor, True), rhs.reshape(-1), check_finite=False).reshape(K, n, 3)
        offset = solved.reshape(-1, 3).take(slot, axis=0) - self.centers
        along = np.einsum("mi,mi->m", offset, self.rays)
        perpendicular = offset - along[:, None] * self.rays
        return np.einsum("mi,mi->m", perpendicular, perpendicular), prior_value(prior, solved.reshape(K, -1))


def _polish_points(observed: np.ndarray, refined: np.ndarray) -> np.ndarray:
    """(P,) the refined points whose observations `observed (F, P)` the polish's cost uses: all of them, or the
    most observed ones where they span more than POLISH_SIZE point-frames."""
    count = int(refined.sum())
    allowed = max(POLISH_MIN_POINTS, POLISH_SIZE // max(len(observed), 1))
    if count <= allowed:
        return refined
    chosen = most_observed(observed, refined, allowed)
    log.info("clock polish on the %d most observed of %d points (%d frames)", allowed, count, len(observed))
    return chosen


def _coordinate_descent(
    cost: _PolishCost, times: np.ndarray, video_index: np.ndarray, correction: ClockCorrection, rates: bool
) -> list[float]:
    """Sweeps over the videos, each video's offset (then rate) by golden-section search with the others held;
    `correction` is updated in place. Returns the cost before and after each sweep."""
    history = [cost(times)]
    current = history[0]  # the cost at the current correction: every search's value at 0, known without a solve
    # (video, kind) -> the correction its last search could not improve: the same search there finds nothing again
    fruitless: dict[tuple[int, str], bytes] = {}
    for _ in range(max(POLISH_SWEEPS, 0)):
        for v in range(len(correction.offset)):
            own = video_index == v
            if own.sum() < 2:
                continue
            period = float(np.median(np.diff(np.sort(times[own]))))
            video_span = float(np.ptp(times[own]))
            if not (period > 0 and video_span > 0):
                continue
            for kind in ("offset", "rate") if rates else ("offset",):
                state = correction.offset.tobytes() + correction.rate.tobytes()
                if fruitless.get((v, kind)) == state:
                    continue
                values = correction.offset if kind == "offset" else correction.rate
                # The rate's bracket moves the video's ends by as much as the offset's moves its middle.
                reach = POLISH_REACH_PERIODS * period * (1.0 if kind == "offset" else 2.0 / video_span)

                def shifted(delta: float, values: np.ndarray = values, v: int = v) -> float:
                    trial = values.copy()
                    trial[v] += delta
                    if values is correction.offset:
                        moved = ClockCorrection(middle=correction.middle, offset=trial, rate=correction.rate)
                    else:
                        moved = ClockCorrection(middle=correction.middle, offset=correction.offset, rate=trial)
                    return cost(moved.apply(times, video_index))

                best, best_cost = _search_from_zero(shifted, current, reach, POLISH_TOLERANCE * reach)
                if best_cost < current:
                    values[v] += best  # the same sum as the search's trial: `current` is its cost exactly
                    current = best_cost
                else:
                    fruitless[v, kind] = state
        history.append(current)
        if history[-2] - history[-1] <= POLISH_STOP * abs(history[-2]):
            break
    return history


def _search_from_zero(
    f: Callable[[float], float], at_zero: float, reach: float, tolerance: float
) -> tuple[float, float]:
    """Minimum of a unimodal f on [-reach, reach] to `tolerance`, f(0) = `at_zero` known: (argument, value).

    Probes +- tolerance / 2 first. Where neither is lower than f(0) the minimum lies within them, i.e. at 0 to the
    tolerance (two solves: the usual case once the clocks are right); otherwise it lies on the lower side, which
    the golden-section search takes."""
    half = tolerance / 2
    for side in (1.0, -1.0):
        probe = f(side * half)
        if probe < at_zero:
            low, high = (0.0, reach) if side > 0 else (-reach, 0.0)
            best, best_value = _golden_search(f, low, high, tolerance)
            return (best, best_value) if best_value < probe else (side * half, probe)
    return 0.0, at_zero


def _golden_search(f: Callable[[float], float], low: float, high: float, tolerance: float) -> tuple[float, float]:
    """Minimum of a unimodal f on [low, high] to `tolerance`: (argument, value)."""
    golden = (np.sqrt(5.0) - 1) / 2
    a, b = high - golden * (high - low), low + golden * (high - low)
    fa, fb = f(a), f(b)
    while high - low > tolerance:
        if fa < fb:
            high, b, fb = b, a, fa
            a = high - golden * (high - low)
            fa = f(a)
        else:
            low, a, fa = a, b, fb
            b = low + golden * (high - low)
            fb = f(b)
    return (a, fa) if fa < fb else (b, fb)
