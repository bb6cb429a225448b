import json

import numpy as np
from synthetic_motion import synthetic_problem, truth_array

from reconstruct.solver.alternation import solve
from reconstruct.temporal import Refinement, TemporalOptions, recover_and_refine


def _restart_clocks(problem):
    """Each video's decoder clock starts at its own first frame, as phones' do: the offsets are unknown."""
    starts = np.array([problem.times[problem.video_index == v].min() for v in range(len(problem.video_names))])
    true_times = problem.times.copy()
    problem.times = problem.times - starts[problem.video_index]
    return true_times, starts


def test_clocks_are_recovered_and_refinement_beats_the_seed_solve_under_noise():
    problem, truth = synthetic_problem(frames=240, points=6, noise_px=1.0)
    true_times, starts = _restart_clocks(problem)
    result = solve(problem)
    temporal = recover_and_refine(problem, result)
    assert temporal.refined
    reference = problem.video_names.index(temporal.clocks.reference)
    error = temporal.times + starts[reference] - true_times
    assert np.median(np.abs(error)) < 0.25 / 30  # a quarter of a camera's frame period
    expected = truth_array(problem, truth)
    seed = np.linalg.norm(result.points - expected, axis=-1)
    refined = np.linalg.norm(temporal.points - expected, axis=-1)
    assert np.median(refined) < np.median(seed)
    assert np.mean(refined < 10.0) >= np.mean(seed < 10.0)
    reference_clock = temporal.clocks.video(temporal.clocks.reference)
    assert abs(reference_clock.offset) < 1e-6 and abs(reference_clock.rate - 1) < 1e-6  # the gauge is kept
    corrections = temporal.report["clock_corrections"]
    assert len(corrections) == len(problem.video_names)
    assert json.dumps(temporal.clocks.to_json(), allow_nan=False)


def test_refinement_none_keeps_the_seed_points_but_reports_clocks():
    problem, _ = synthetic_problem(frames=120, points=4)
    _restart_clocks(problem)
    result = solve(problem)
    temporal = recover_and_refine(problem, result, TemporalOptions(refinement=Refinement.NONE))
    assert not temporal.refined
    np.testing.assert_array_equal(temporal.points, result.points)
    assert np.all(np.isfinite(temporal.times))


def test_a_clock_polish_whose_cost_rises_or_rate_runs_away_is_rejected():
    from reconstruct.temporal import _plausible

    assert _plausible([10.0, 9.0, 9.05], np.array([0.0, 1e-4]), 0.01)
    assert not _plausible([10.0, 9.0, 1e6], np.array([0.0, 1e-4]), 0.01)  # the cost exploded
    assert not _plausible([10.0, 9.0], np.array([0.0, 0.24]), 0.01)  # a clock stretched by 24 %
    assert not _plausible([10.0, float("nan")], np.array([0.0, 0.0]), 0.01)
    # exact data: a negative cost that stays where it was is no rise (FreeMoCap's rig, projected without noise)
    assert _plausible([-0.008739, -0.008739], np.array([0.0, 0.0]), 0.01)
    assert not _plausible([-1.0, -0.5], np.array([0.0, 0.0]), 0.01)


def test_a_track_clock_a_cycle_off_loses_to_the_links_clock(monkeypatch):
    """The track search locked on another cycle for one video (its clock 30 frame periods off) and was kept against
    W's links: the refinement measures both and keeps the links', whose trajectories meet their rays."""
    import copy

    import reconstruct.clocks.estimate as estimate_module

    problem, truth = synthetic_problem(frames=240, points=8, noise_px=1.0)
    _restart_clocks(problem)
    result = solve(problem)
    search = estimate_module.search_clocks

    def one_cycle_off(problem, own, ref, *args, **kwargs):
        found = copy.deepcopy(search(problem, own, ref, *args, **kwargs))
        v = (ref + 1) % len(problem.video_names)
        found.params.coef[v][0] += 30 * np.median(np.diff(np.sort(own[problem.video_index == v])))
        return found

    right = recover_and_refine(problem, result)
    assert "links_clocks" not in right.report
    monkeypatch.setattr(estimate_module, "search_clocks", one_cycle_off)
    chosen = recover_and_refine(problem, result)

    entry = chosen.report["links_clocks"]
    # the wrong clock's trajectories bend through every ray (their residual is the smaller one); the error they predict
    # for a ray they did not see is what gives them away
    assert entry["kept"] == "links" and entry["predicted_px"]["links"] < 0.5 * entry["predicted_px"]["tracks"]
    assert chosen.report["path"] == "clocks"
    assert chosen.clocks.video(entry["videos"][0]).method == "links"
    assert any("kept the tracks' clock" in w for w in chosen.clocks.warnings)  # the evidence stays in the report
    expected = truth_array(problem, truth)
    error = np.nanmedian(np.linalg.norm(chosen.points - expected, axis=-1))
    assert error < 1.2 * np.nanmedian(np.linalg.norm(right.points - expected, axis=-1))


def test_a_rejected_clock_polish_says_which_condition_failed() -> None:
    """The warning said "its cost rose or a rate moved" on offset-only clocks, where no rate can move."""
    import numpy as np

    from reconstruct.temporal import _rejection

    assert _rejection([10.0, 12.0], np.zeros(3), 0.05) == "its cost rose from 10 to 12"
    assert _rejection([10.0, 9.0], np.array([0.0, 0.08]), 0.05) == "a rate moved by 8.0 %, over 5 %"
    assert _rejection([10.0, float("nan")], np.zeros(3), 0.05) == "its cost was not finite"
