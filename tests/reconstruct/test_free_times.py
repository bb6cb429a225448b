"""Refinement without a clock model (issue 17): the polished frame order and its fixed times, checked before they
are used, and the retimed free times as their fallback."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_motion import share_within_10mm, smooth_motion

from reconstruct.free_times import (
    NOMINAL_PERIOD,
    order_path_length,
    polish_order,
    rank_times,
    spectral_times,
)
from reconstruct.temporal import recover_and_refine
from reconstruct.time_checks import RefinementJudge
from reconstruct.trajectory import RefineOptions


def _interleaved(frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A motion's frames dealt round-robin to 3 videos: (true order (F,), video_index (F,), points (F, P, 3))."""
    points = smooth_motion(frames=frames, points=5, seed=2)
    video = np.arange(frames) % 3
    return np.arange(frames), video, points


def test_polish_order_restores_swaps_between_videos():
    truth, video, points = _interleaved(90)
    order = truth.copy()
    for i in range(0, 84, 7):  # neighbours of different videos swapped: a wrong interleaving
        order[[i, i + 1]] = order[[i + 1, i]]
    polished = polish_order(order, points, video)
    assert np.array_equal(polished, truth)
    assert order_path_length(polished, points) < order_path_length(order, points)


def test_polish_order_keeps_each_videos_frame_order():
    truth, video, points = _interleaved(60)
    rng = np.random.default_rng(0)
    noisy = points + rng.normal(scale=30.0, size=points.shape)  # a poor seed: moves must still respect the videos
    polished = polish_order(truth, noisy, video)
    for v in range(3):
        assert np.array_equal(polished[video[polished] == v], truth[video == v])


def test_rank_times_are_evenly_spaced_in_the_order():
    order = np.array([2, 0, 3, 1])
    times = rank_times(order, num_videos=2)
    assert np.allclose(times[order], np.arange(4) * NOMINAL_PERIOD / 2)


def test_the_polished_order_beats_the_spectral_order(no_times):
    problem, _, seed, true_times = no_times
    spectral = spectral_times(seed.W.to_csc(), problem.video_index, problem.frames)
    start = np.argsort(spectral, kind="stable")
    polished = polish_order(start, seed.points, problem.video_index)
    true_rank = np.argsort(np.argsort(true_times, kind="stable"), kind="stable")

    def misplaced(order: np.ndarray) -> int:
        rank = np.empty(len(order), dtype=np.int64)
        rank[order] = np.arange(len(order))
        return int(np.sum(rank != true_rank))

    assert misplaced(polished) <= misplaced(start)


def test_the_judge_uses_the_order_only_when_it_fits_and_says_so(no_times):
    problem, _, seed, _ = no_times
    judge = RefinementJudge(problem, seed, RefineOptions())
    free = judge.free()
    report = judge.free_report()
    fit = report["free_times_order_fit"]
    assert fit is not None and fit["name"] == "order_fit"
    assert report["free_times_source"] == ("order" if fit["passed"] else "retimed")
    if fit["passed"]:
        assert free.ordered is free.result and free.ordered_times is free.times
        assert judge.seed_agreement(free.result, "free_times")[0].name == "order_fit"
    assert report["free_times_order_path"][1] <= report["free_times_order_path"][0]


def test_on_the_order_a_far_point_is_kept_only_where_it_fits_its_ray(no_times):
    """Keep-seed rule of the polished order: a frame moved along its rays (still fitting them) keeps the refined
    points, a frame moved off its rays gets the seed's points back."""
    problem, _, seed, _ = no_times
    judge = RefinementJudge(problem, seed, RefineOptions())
    free = judge.free()
    if judge.free_report()["free_times_source"] != "order":
        pytest.skip("the polished order was not used on this capture")
    refined = free.result
    centers = problem.centers
    along, off = 10, 20
    refined.points[along] = centers[along] + 1.2 * (refined.points[along] - centers[along])
    refined.points[off] = refined.points[off] + np.array([300.0, 0.0, 0.0])
    points, _ = judge.keep_seed_where_far(refined)
    seen = np.isfinite(problem.uv[along, :, 0]) & np.isfinite(problem.uv[off, :, 0])
    assert np.allclose(points[along][seen], refined.points[along][seen])
    assert np.allclose(points[off][seen], seed.points[off][seen])


def test_an_order_that_fits_worse_than_its_start_is_not_used(no_times, monkeypatch):
    """Fixed times whose residual exceeds the spectral order's by more than the clock-cost margin fall back to the
    retimed free times, and the report names the failed check."""
    problem, _, seed, _ = no_times
    import reconstruct.time_checks as time_checks

    monkeypatch.setattr(time_checks, "CLOCK_COST_FACTOR", 0.0)
    monkeypatch.setattr(time_checks, "CLOCK_COST_PX", -1.0)
    monkeypatch.setattr(time_checks, "FIT_PX", -1.0)
    judge = RefinementJudge(problem, seed, RefineOptions())
    free = judge.free()
    report = judge.free_report()
    assert report["free_times_source"] == "retimed" and not report["free_times_order_fit"]["passed"]
    assert free.result is not free.ordered
    assert [c.name for c in judge.seed_agreement(free.result, "free_times")] == ["free_times_seed_shift"]


def test_no_times_default_solve_is_never_below_the_seed(no_times):
    problem, truth, seed, _ = no_times
    temporal = recover_and_refine(problem, seed)
    assert temporal.report["path"] in ("free_times", "seed")
    assert share_within_10mm(temporal.points, truth) >= share_within_10mm(seed.points, truth)
    for v in range(len(problem.video_names)):  # each video's frames stay in order
        own = np.flatnonzero(problem.video_index == v)
        assert np.all(np.diff(temporal.times[own[np.argsort(problem.frames[own])]]) > 0)
