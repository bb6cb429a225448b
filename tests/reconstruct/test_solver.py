import itertools

import numpy as np
import pytest
from synthetic_motion import synthetic_problem, truth_array

from dynrecon.errors import NotEnoughDataError
from reconstruct.problem import build_problem
from reconstruct.solver import SolverOptions, solve
from reconstruct.xstep import RayConstraint
from tracking.tracks import Tracks


@pytest.mark.parametrize("constraint", list(RayConstraint))
def test_noise_free_smooth_motion_is_recovered(constraint):
    problem, truth = synthetic_problem(frames=160, points=6)
    result = solve(problem, SolverOptions(constraint=constraint))
    error = np.linalg.norm(result.points - truth_array(problem, truth), axis=-1)
    assert np.mean(error < 10.0) > 0.99
    assert np.median(error) < 1.0  # mm, cameras ~2 m away
    # The recovered neighbours are frames of other videos close in time.
    times = np.array([truth.extra["time"][truth.index()[(v, int(f))], 0]
                      for v, f in zip(problem.frame_videos, problem.frames, strict=True)])
    gaps = [abs(times[j] - times[f]) for f in range(problem.num_frames) for j in result.W.column(f, 0.05)[0]]
    assert np.median(gaps) <= 2.5 / 120


def test_defaults_handle_noise_and_missing_observations():
    problem, truth = synthetic_problem(frames=160, points=6, noise_px=1.0, miss=0.2)
    result = solve(problem)
    error = np.linalg.norm(result.points - truth_array(problem, truth), axis=-1)
    assert np.mean(error < 20.0) > 0.95
    assert np.all(np.isfinite(result.points))


def test_outputs_are_in_input_units_and_cost_decreases_in_the_final_stage():
    problem, _ = synthetic_problem(frames=100, points=5)
    result = solve(problem)
    assert result.normalization.scale > 100  # mm input, normalized internally
    final = result.stages[-1].cost
    assert final[-1] <= final[0]
    assert result.residual.shape == (problem.num_frames,)


def test_point_seen_in_one_video_is_left_empty_with_a_warning(caplog):
    problem, _ = synthetic_problem(frames=60, points=4)
    problem.uv[problem.video_index != 0, 2] = np.nan
    result = solve(problem, SolverOptions(max_iterations=3))
    assert np.all(np.isnan(result.points[:, 2]))
    assert np.all(np.isfinite(result.points[:, [0, 1, 3]]))
    assert any("fewer than two videos" in r.message for r in caplog.records)


def test_no_reconstructable_point_is_an_error():
    problem, _ = synthetic_problem(frames=30, points=2)
    problem.uv[problem.video_index != 0] = np.nan
    with pytest.raises(NotEnoughDataError, match="two different videos"):
        solve(problem)


def test_fewer_than_two_videos_is_an_error():
    problem, _ = synthetic_problem(frames=30, points=2)
    from synthetic_motion import simulate_capture, smooth_motion

    from reconstruct.simulate import SimulationOptions

    capture = simulate_capture(smooth_motion(20, 2), 120.0, SimulationOptions(cameras=2))
    capture.cameras.videos[1].frames.clear()
    with pytest.raises(NotEnoughDataError, match="at least 2"):
        build_problem(capture.cameras, capture.tracks)
    assert problem.num_frames == 30
    assert isinstance(capture.tracks, Tracks)


def test_anderson_acceleration_keeps_the_cost_monotone_and_needs_fewer_alternations():
    problem, truth = synthetic_problem(frames=160, points=6)
    plain = solve(problem, SolverOptions(anderson_memory=0))
    mixed = solve(problem, SolverOptions())
    final = mixed.stages[-1].cost
    assert all(b <= a * (1 + 1e-12) for a, b in itertools.pairwise(final))
    assert mixed.stages[-1].iterations < plain.stages[-1].iterations
    assert final[-1] <= plain.stages[-1].cost[-1] * 1.01
    for result in (plain, mixed):
        error = np.linalg.norm(result.points - truth_array(problem, truth), axis=-1)
        assert np.mean(error < 10.0) > 0.99


@pytest.mark.parametrize("lambda2", [0.0, 0.1])
def test_total_cost_data_and_smoothness_terms_equal_the_x_step_quadratic_form(lambda2):
    import scipy.sparse as sp

    from reconstruct.solver import total_cost
    from reconstruct.xstep import quadratic_form

    rng = np.random.default_rng(7)
    F, P = 30, 4
    video_index = np.repeat([0, 1, 2], 10)
    points = rng.normal(size=(F, P, 3))
    W = sp.random(F, F, density=0.2, random_state=1, format="csc")
    nan_rays = np.full((F, P, 3), np.nan)  # no ray term
    Q = quadratic_form(W, video_index, P, lambda2)
    shapes = points.reshape(F, -1)
    asym = (W - W.T).toarray()
    expected = float(np.sum(shapes * (Q @ shapes))) + 0.05 / F * np.sum(asym**2)
    cost = total_cost(points, W, np.zeros((F, 3)), nan_rays, video_index, 0.05, lambda2, 100.0, RayConstraint.SOFT)
    np.testing.assert_allclose(cost, expected, rtol=1e-12)
