"""Time hypotheses are checked before they are trusted: every rejection path falls back, says so, and is never
worse than the seed solve (issue 17)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from synthetic_motion import share_within_10mm, synthetic_problem, truth_array

from reconstruct.clocks.estimate import ClockOptions
from reconstruct.clocks.model import Clocks, TimeSource
from reconstruct.free_times import gap_spread, spectral_times
from reconstruct.solver.alternation import solve
from reconstruct.temporal import TemporalOptions, recover_and_refine
from reconstruct.time_checks import MIN_DISTINCTNESS, RefinementJudge, clock_checks
from reconstruct.trajectory import RefineOptions, RefineResult


def test_no_fps_and_no_times_refines_without_a_clock_model_and_beats_the_seed(no_times, caplog):
    problem, truth, seed, _ = no_times
    with caplog.at_level(logging.WARNING):
        temporal = recover_and_refine(problem, seed)
    report = temporal.report
    assert report["path"] == "free_times"
    failed = [c for c in report["checks"] if not c["passed"]]
    assert failed and failed[0]["name"] in ("link_residual", "track_distinctness")
    assert "clock model not used" in caplog.text and failed[0]["name"] in caplog.text
    assert share_within_10mm(temporal.points, truth) >= share_within_10mm(seed.points, truth)
    assert np.median(np.linalg.norm(temporal.points - truth, axis=-1)) < np.median(
        np.linalg.norm(seed.points - truth, axis=-1)
    )
    for v in range(len(problem.video_names)):  # per-frame times keep each video's frame order
        own = np.flatnonzero(problem.video_index == v)
        assert np.all(np.diff(temporal.times[own[np.argsort(problem.frames[own])]]) > 0)


def test_irregular_frames_with_a_false_nominal_fps_are_refused(no_times, caplog):
    """Frames without decoder times that claim an even 30 fps while the captures were random: the clock model
    fails its checks and the solve is not worse than the seed."""
    problem, truth, seed, _ = no_times
    claimed = ClockOptions(fps=dict.fromkeys(problem.video_names, 30.0))  # what a wrong nominal rate implies
    with caplog.at_level(logging.WARNING):
        temporal = recover_and_refine(problem, seed, TemporalOptions(clocks=claimed))
    assert {c.time_source for c in temporal.clocks.videos} == {TimeSource.FPS}
    assert temporal.report["path"] in ("free_times", "seed")
    assert any(not c["passed"] for c in temporal.report["checks"]) and "clock model not used" in caplog.text
    assert share_within_10mm(temporal.points, truth) >= share_within_10mm(seed.points, truth)


def test_a_clock_search_without_a_clear_winner_is_not_used(no_times):
    problem, _, seed, _ = no_times
    clocks = recover_and_refine(problem, seed).clocks
    unclear = Clocks(**{**{f.name: getattr(clocks, f.name) for f in dataclasses.fields(Clocks)}})
    unclear.diagnostics = {**clocks.diagnostics, "link_scale_s": 0.0, "track_distinctness": 1.01}
    checks = {c.name: c for c in clock_checks(problem, unclear)}
    assert not checks["track_distinctness"].passed and checks["track_distinctness"].limit == MIN_DISTINCTNESS
    assert "runner-up" in checks["track_distinctness"].sentence()


def test_a_refinement_that_raises_the_residual_is_rejected(no_times):
    """Trajectories on the clocks that fit their rays much worse than free per-frame times fail `clock_fit`, and
    a refinement that moves the seed's points far beyond its own residual fails the seed-agreement check."""
    problem, _, seed, _ = no_times
    judge = RefinementJudge(problem, seed, RefineOptions())
    good = judge.free().result
    off = np.random.default_rng(0).normal(scale=30.0, size=seed.points.shape)  # 30 mm at ~3 m: several px
    worse = RefineResult(**{**{f.name: getattr(good, f.name) for f in dataclasses.fields(RefineResult)}})
    worse.points = seed.points + off
    assert judge.clock_fit(good)[0].passed
    fit = judge.clock_fit(worse)[0]
    assert not fit.passed and fit.value > fit.limit
    assert judge.seed_agreement(good, "free_times")[0].passed
    # On the rays but at other depths: fits perfectly, disagrees with the seed far beyond its residual.
    centers = problem.centers[:, None, :]
    shifted = dataclasses.replace(worse, points=centers + 1.02 * (seed.points - centers))
    assert not judge.seed_agreement(shifted, "free_times")[0].passed


def test_decoder_times_keep_the_clock_path():
    problem, truth = synthetic_problem(frames=160, points=5, seed=1)
    seed = solve(problem)
    temporal = recover_and_refine(problem, seed)
    assert temporal.report["path"] == "clocks"
    assert all(c["passed"] for c in temporal.report["checks"])
    expected = truth_array(problem, truth)
    assert share_within_10mm(temporal.points, expected) >= share_within_10mm(seed.points, expected)


def test_spectral_times_follow_the_capture_order(no_times):
    problem, _, seed, true_times = no_times
    times = spectral_times(seed.W.to_csc(), problem.video_index, problem.frames)
    rank, true_rank = np.argsort(np.argsort(times)), np.argsort(np.argsort(true_times))
    assert np.corrcoef(rank, true_rank)[0, 1] > 0.99
    assert gap_spread(times, problem.video_index, problem.frames) > 0.2  # random assignment: uneven gaps
    assert gap_spread(true_times, problem.video_index, problem.frames) > 0.2
