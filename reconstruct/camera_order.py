"""Are the cameras given to the right videos? A test of the other orders of static cameras, before the solve.

A calibration file names its cameras by serial number or `cam_N`; where the names do not match the videos,
`import-calibration` matches them in the order given, and a wrong order is not an error the files can show. The
tracks can: with the right cameras some offset brings every pair of videos' rays together, with a swapped one no
offset does. Where some pair of videos misfits at its best offset, every other order of the static cameras is
scored by the same pair search; an order whose pairs fit at under BETTER_SHARE of the summed cost of the given
order and of the next best is the user's mistake, said in one line with the order that fits (docs/clocks.md,
"Which camera filmed which video").
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from reconstruct.clocks.model import TimeSource, frame_periods, own_times
from reconstruct.clocks.search import MISFIT_SHARE, SearchOptions, VideoRays, search_pair, video_tracks
from reconstruct.solver.problem import Problem

__all__ = ["CameraOrder", "check_camera_order", "score_camera_order"]

log = logging.getLogger(__name__)

MAX_VIDEOS = 6  # 6! orders from 450 pair searches; beyond, the test is skipped with a note
ORDER_QUERIES = 50  # frames per video and direction of each pair search here: a third of the clock search's
BETTER_SHARE = 0.75  # the order found: summed pair cost under this share of the given order's and the next best's
_STATIC_TOL = 1e-9


@dataclasses.dataclass(kw_only=True)
class CameraOrder:
    """The test's outcome. `order[v]`: the video whose camera video v fits (the identity where the given fits)."""

    order: tuple[int, ...]
    given_costs: list[float]  # (pairs,) px^2, each pair's best truncated cost with the cameras as given
    best_costs: list[float]  # the same under `order`
    cap: float  # px^2, a pair's largest cost (the truncation)
    runner_up: tuple[int, ...] | None = None  # the order of the next lowest summed cost, where others were tried
    runner_up_costs: list[float] | None = None

    @property
    def swapped(self) -> bool:
        return self.order != tuple(range(len(self.order)))


def _static_cameras(problem: Problem) -> list[int] | None:
    """Each video's first row, where every video's frames share one camera (K, R, t, lens); else None."""
    first = []
    for v in range(len(problem.video_names)):
        rows = np.flatnonzero(problem.video_index == v)
        if not len(rows):
            return None
        r0 = rows[0]
        for array in (problem.K, problem.R, problem.t):
            if np.abs(array[rows] - array[r0]).max() > _STATIC_TOL * max(1.0, float(np.abs(array[r0]).max())):
                return None
        lens = problem.dist[r0]
        if any(not _same_lens(problem.dist[r], lens) for r in rows):
            return None
        first.append(int(r0))
    return first


def _same_lens(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=0, atol=_STATIC_TOL))


def _with_camera(problem: Problem, rows: list[int], camera: int) -> Problem:
    """The problem with every frame given the camera of video `camera` (its row `rows[camera]`)."""
    r = rows[camera]
    F = problem.num_frames
    return dataclasses.replace(
        problem,
        K=np.broadcast_to(problem.K[r], (F, 3, 3)).copy(),
        R=np.broadcast_to(problem.R[r], (F, 3, 3)).copy(),
        t=np.broadcast_to(problem.t[r], (F, 3)).copy(),
        dist=[problem.dist[r]] * F,
    )


def score_camera_order(
    problem: Problem,
    fps: Mapping[str, float] | None = None,
    options: SearchOptions | None = None,
) -> CameraOrder | None:
    """Score the cameras as given and, where some pair of videos misfits, every other order of the cameras of the
    videos with tracks (the others keep theirs: nothing tells them apart); None where the test does not apply (a
    moving camera, one video, more than MAX_VIDEOS videos, no tracked point)."""
    options = dataclasses.replace(options or SearchOptions(), max_queries=ORDER_QUERIES)  # orders differ grossly
    N = len(problem.video_names)
    rows = _static_cameras(problem)
    if rows is None or N < 2:
        return None
    if N > MAX_VIDEOS:
        log.info("camera order: %d videos, over %d: the orders of their cameras are not tested", N, MAX_VIDEOS)
        return None
    own, sources = own_times(problem, fps)
    periods = frame_periods(own, problem.video_index, N)
    counts = problem.observed.sum(axis=0)
    points = np.argsort(-counts, kind="stable")[: options.max_points]
    points = points[counts[points] > 0]
    if not len(points):
        return None
    cap = options.inlier_px**2
    given_tracks = video_tracks(problem, own, points)
    pairs = [(v, u) for v in range(N) for u in range(v + 1, N)]
    given = {pair: _cost(given_tracks, pair, options, periods, sources) for pair in pairs}
    identity = tuple(range(N))
    given_costs = [given[pair] for pair in pairs]
    finite = [c for c in given_costs if np.isfinite(c)]
    if not finite or max(finite) < MISFIT_SHARE * cap:
        return CameraOrder(order=identity, given_costs=given_costs, best_costs=given_costs, cap=cap)
    seen = np.asarray(problem.observed[:, points].any(axis=1))
    movable = [v for v in range(N) if seen[problem.video_index == v].any()]
    # tracks[c][v]: video v's rays through video c's camera
    tracks = {c: video_tracks(_with_camera(problem, rows, c), own, points) for c in movable}
    costs: dict[tuple[int, int, int, int], float] = {}
    for v, u in pairs:
        if v not in tracks or u not in tracks:
            continue  # an untracked video's pairs cost the cap in every order
        for a, b in itertools.permutations(movable, 2):
            mixed = list(given_tracks)
            mixed[v], mixed[u] = tracks[a][v], tracks[b][u]
            costs[v, u, a, b] = given[v, u] if (a, b) == (v, u) else _cost(mixed, (v, u), options, periods, sources)
    orders = []
    for cameras in itertools.permutations(movable):
        order = list(identity)
        for v, c in zip(movable, cameras, strict=True):
            order[v] = c
        orders.append(tuple(order))

    def pair_costs(order: tuple[int, ...]) -> list[float]:
        return [costs.get((v, u, order[v], order[u]), given[v, u]) for v, u in pairs]

    totals = sorted((_total(pair_costs(order), cap), order) for order in orders)
    if len(totals) < 2:
        return CameraOrder(order=identity, given_costs=given_costs, best_costs=given_costs, cap=cap)
    (_, best), (_, second) = totals[0], totals[1]
    return CameraOrder(
        order=best,
        given_costs=given_costs,
        best_costs=pair_costs(best),
        cap=cap,
        runner_up=second,
        runner_up_costs=pair_costs(second),
    )


def _cost(
    tracks: list[VideoRays],
    pair: tuple[int, int],
    options: SearchOptions,
    periods: np.ndarray,
    sources: list[TimeSource],
) -> float:
    """A pair's best truncated cost over its offsets; inf where the videos do not overlap enough."""
    found = search_pair(tracks, pair[0], pair[1], options, periods, sources)
    return found.cost if found is not None else float("inf")


def _total(costs: list[float], cap: float) -> float:
    """Summed pair costs, a pair without overlap counted at the cap (it neither fits nor refutes)."""
    return float(sum(c if np.isfinite(c) else cap for c in costs))


def check_camera_order(
    problem: Problem,
    cameras_path: Path | None,
    fps: Mapping[str, float] | None = None,
    options: SearchOptions | None = None,
    every_video: list[str] | None = None,
) -> CameraOrder | None:
    """Raise InputError where the tracks fit one other order of the cameras far better than the given one: its
    summed pair cost under BETTER_SHARE of the given order's and of the next best order's; warn where two orders
    fit about as well (a rig whose swap is nearly a rotation or mirror of it). `every_video`: the cameras file's
    videos, where the solve takes some of them (the order to import in is then not named)."""
    found = score_camera_order(problem, fps, options)
    if found is None or not found.swapped:
        return found
    # pairs without overlap in every order (an untracked video's) say nothing either way
    lists = [found.given_costs, found.best_costs, found.runner_up_costs or found.given_costs]
    informative = [any(np.isfinite(c[i]) for c in lists) for i in range(len(found.given_costs))]
    given, best, second = (
        _total([c for c, keep in zip(costs, informative, strict=True) if keep], found.cap) for costs in lists
    )
    if best >= BETTER_SHARE * given:
        return found
    names = problem.video_names
    if found.runner_up is not None and best >= BETTER_SHARE * second:
        log.warning(
            "%s: the cameras fit these tracks better in other orders than the one given, two about as well "
            "(%s; %s): check which camera filmed which video",
            cameras_path or "cameras",
            _moved(names, found.order),
            _moved(names, found.runner_up),
        )
        return found
    fix = "give each video its own camera (import-calibration matches them by order where the names differ)"
    if every_video is None or list(every_video) == names:
        # import-calibration gave the k-th camera to the k-th video: the camera of video c goes to the video fitting it
        wanted = [names[found.order.index(c)] for c in range(len(names))]
        fix = (
            "where import-calibration matched the calibration's cameras to the videos by order, run it again with "
            f"the videos in the order {' '.join(wanted)}"
        )
    raise InputError(
        cameras_path,
        f"the cameras fit these tracks in another order: {_moved(names, found.order)} (the pairs of videos' rays, "
        f"each at its best offset, meet within truncated mean squared gaps of {_listed(found.best_costs)} px^2 so, "
        f"against {_listed(found.given_costs)} as given, of at most {found.cap:.0f})",
        fix=fix,
    )


def _moved(names: list[str], order: tuple[int, ...]) -> str:
    return ", ".join(f"{names[v]} fits {names[c]}'s camera" for v, c in enumerate(order) if c != v) or "as given"


def _listed(costs: list[float]) -> str:
    return ", ".join("-" if not np.isfinite(c) else f"{c:.1f}" for c in costs)
