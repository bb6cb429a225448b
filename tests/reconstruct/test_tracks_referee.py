"""The referee of the tracks path beyond a few points: the seed solve on a subsample must agree with the tracks'
clocks, or the seed solve runs (reconstruct/tracks_referee.py)."""

import dataclasses
import threading

import numpy as np
import pytest
from synthetic_motion import smooth_motion, synthetic_problem, truth_array

from dynrecon.beside import NO_FORK, fork_is_safe
from reconstruct import tracks_path, tracks_referee
from reconstruct.clocks.estimate import estimate_clocks_from_tracks
from reconstruct.inputs import build_problem
from reconstruct.solver.alternation import SolverOptions
from reconstruct.stage import SolveOptions, solve
from reconstruct.temporal import TemporalOptions
from reconstruct.tracks_referee import REFEREE_FRAMES, REFEREE_STEP, referee_check, subsample, take_frames
from simulation.simulate import SimulationOptions, simulate_capture

POINTS = 24  # beyond TemporalOptions.tracks_path_max_points: the refereed tracks path


@pytest.fixture(scope="module")
def capture():
    capture = simulate_capture(smooth_motion(100, POINTS, seed=2), 120.0, SimulationOptions(seed=2))
    problem = build_problem(capture.cameras, capture.tracks, point_names=capture.truth.point_names)
    options = TemporalOptions().clock_options(problem)
    return capture, problem, options, estimate_clocks_from_tracks(problem, options)


def test_right_clocks_are_confirmed_and_the_solve_takes_the_tracks_path(capture):
    simulated, problem, options, clocks = capture
    check, report = referee_check(problem, clocks, SolverOptions(), options)
    assert check.passed and check.value < 0.2, check.sentence()
    assert report["frames"] == subsample(problem, clocks.global_time).size < problem.num_frames
    assert set(report["videos"]) == set(problem.video_names)

    result = solve(simulated.cameras, simulated.tracks)
    temporal = result.report["temporal"]
    assert temporal["path"] == "tracks", temporal.get("reason")
    assert {c["name"] for c in temporal["checks"]} >= {"referee", "track_distinctness"}
    assert temporal["referee"]["frames"] == report["frames"]
    # a short capture: the referee's subsample needs no clocks, and it solved beside the track search
    assert temporal["referee"]["beside"] == "track search and refinement"
    assert set(temporal["referee"]["videos"]) == set(report["videos"])
    error = np.linalg.norm(result.temporal.points - truth_array(result.problem, simulated.truth), axis=-1)
    assert np.nanmedian(error) < 1.0


def test_the_referee_in_a_process_gives_what_it_gives_in_a_thread(capture, monkeypatch):
    simulated = capture[0]
    if not fork_is_safe():
        pytest.skip(f"fork is not used here: threads {threading.enumerate()} alive, or not Linux")
    forked = solve(simulated.cameras, simulated.tracks)
    monkeypatch.setenv(NO_FORK, "1")
    threaded = solve(simulated.cameras, simulated.tracks)
    assert forked.report["temporal"]["referee"]["ran_in"] == "process"
    assert threaded.report["temporal"]["referee"]["ran_in"] == "thread"
    for key in ("videos", "frames"):
        assert forked.report["temporal"]["referee"][key] == threaded.report["temporal"]["referee"][key]
    np.testing.assert_array_equal(forked.temporal.points, threaded.temporal.points)


def test_a_windowed_referee_starts_after_the_track_search(capture, monkeypatch):
    # beyond REFEREE_FRAMES subsampled frames the window needs the tracks' clocks: the referee runs beside the
    # refinement only, and gives what it gives in a thread
    simulated = capture[0]
    monkeypatch.setattr(tracks_referee, "REFEREE_FRAMES", 28)
    forked = solve(simulated.cameras, simulated.tracks)
    referee = forked.report["temporal"]["referee"]
    assert forked.report["temporal"]["path"] == "tracks" and referee["frames"] == 28
    assert referee["beside"] == "refinement"
    monkeypatch.setenv(NO_FORK, "1")
    threaded = solve(simulated.cameras, simulated.tracks)
    assert threaded.report["temporal"]["referee"]["ran_in"] == "thread"
    assert threaded.report["temporal"]["referee"]["videos"] == referee["videos"]
    np.testing.assert_array_equal(forked.temporal.points, threaded.temporal.points)


def test_a_clock_a_cycle_off_is_refused_and_the_seed_solve_runs(capture, monkeypatch):
    simulated, problem, options, clocks = capture
    wrong = dataclasses.replace(clocks, global_time=clocks.global_time.copy())
    wrong.global_time[problem.video_index == 2] += 0.5  # half a second: many frame periods
    check, report = referee_check(problem, wrong, SolverOptions(), options)
    assert not check.passed and check.value > 3.0
    assert abs(report["videos"][problem.video_names[2]]["difference_s"] + 0.5) < 0.05

    # the same wrong clock from the track search (its own checks pass): refused, and the seed solve's answer kept
    monkeypatch.setattr(tracks_path, "estimate_clocks_from_tracks", lambda *_: dataclasses.replace(wrong))
    result = solve(simulated.cameras, simulated.tracks)
    temporal = result.report["temporal"]
    assert temporal["path"] != "tracks" and temporal["tracks_path"]["failed"] == "referee"
    assert "referee" in temporal["reason"] and temporal["tracks_path"]["referee"]["videos"]
    error = np.linalg.norm(result.temporal.points - truth_array(result.problem, simulated.truth), axis=-1)
    assert np.nanmedian(error) < 1.0


def test_without_the_referee_beyond_few_points_the_seed_solve_runs(capture):
    simulated = capture[0]
    temporal = dataclasses.replace(TemporalOptions(), tracks_path_refereed=False)
    result = solve(simulated.cameras, simulated.tracks, SolveOptions(temporal=temporal))
    assert result.report["temporal"]["path"] != "tracks" and "referee" not in result.report["temporal"]
    error = np.linalg.norm(result.temporal.points - truth_array(result.problem, simulated.truth), axis=-1)
    assert np.nanmedian(error) < 1.0


def test_subsample_takes_every_step_th_frame_and_a_middle_window_of_long_captures():
    problem, _ = synthetic_problem(frames=40, points=2, seed=0)
    index = subsample(problem, problem.times)
    for v in range(len(problem.video_names)):
        own = np.sort(problem.frames[problem.video_index == v])
        assert np.array_equal(np.sort(problem.frames[index][problem.video_index[index] == v]), own[::REFEREE_STEP])
    # one long video (every frame its own rank): beyond REFEREE_FRAMES subsampled frames, a window at the middle
    tiled = take_frames(problem, np.tile(np.arange(problem.num_frames), 2 * REFEREE_FRAMES * REFEREE_STEP // 40))
    count = tiled.num_frames
    long = dataclasses.replace(tiled, video_index=np.zeros(count, dtype=np.int64), frames=np.arange(count))
    times = np.linspace(0.0, 100.0, count)
    chosen = subsample(long, times)
    assert chosen.size == REFEREE_FRAMES and np.all(chosen % REFEREE_STEP == 0)
    assert abs(np.median(times[chosen]) - 50.0) < 1.0


def test_a_subsample_that_cannot_be_solved_confirms_nothing(capture, monkeypatch):
    _, problem, options, clocks = capture

    def singular(*_):
        raise np.linalg.LinAlgError("singular")

    monkeypatch.setattr(tracks_referee, "solve", singular)
    check, report = referee_check(problem, clocks, SolverOptions(), options)
    assert not check.passed and check.value == np.inf
    assert all(v["periods"] is None for name, v in report["videos"].items() if name != clocks.reference)


def test_a_refinement_that_fails_on_the_tracks_clocks_falls_back_to_the_seed_solve(capture, monkeypatch):
    simulated = capture[0]

    def broken(*_):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(tracks_path, "refine_on_clocks", broken)
    result = solve(simulated.cameras, simulated.tracks)
    temporal = result.report["temporal"]
    assert temporal["path"] != "tracks" and temporal["tracks_path"]["failed"] == "refinement"
    assert "refinement" in temporal["reason"]
    assert "Singular matrix" in next(c for c in temporal["tracks_path"]["checks"] if not c["passed"])["meaning"]
    error = np.linalg.norm(result.temporal.points - truth_array(result.problem, simulated.truth), axis=-1)
    assert np.nanmedian(error) < 1.0
