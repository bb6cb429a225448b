"""reconstruct.trajectory: smoothing-spline trajectories through viewing rays on known global times."""

from __future__ import annotations

import numpy as np
import pytest
from refine_capture import capture, error_mm, round_robin, start_points

from dynrecon.errors import InputError
from reconstruct import trajectory
from reconstruct.spline_system import prior_bands, time_nodes
from reconstruct.trajectory import (
    GCV_PASSES,
    IRLS_ITERATIONS,
    SMOOTHNESS_GRID,
    RefineOptions,
    RobustLoss,
    SmoothnessRule,
    predicted_pair,
    predicted_px,
    refine,
)


def test_noise_free_rays_reproduce_the_truth_at_a_sparse_rate() -> None:
    # 30 captures per second overall = 7.5 Hz per camera: each instant has one ray, only the prior fixes depth.
    times, camera_of = round_robin(75, 30.0)
    problem, truth = capture(times, camera_of)
    result = refine(problem, start_points(problem, truth), times)
    errors = error_mm(result.points, truth)
    assert np.median(errors) < 1.0
    assert np.max(errors[5:-5]) < 5.0  # the ends extrapolate the spline
    assert np.all(result.weights[problem.observed] > 0.99)
    assert not result.outliers.any()


def test_noisy_rays_are_improved_over_the_input() -> None:
    times, camera_of = round_robin(240, 120.0)
    problem, truth = capture(times, camera_of, noise_px=2.0)
    # The input: each point on its own noisy ray at the true depth (what a per-frame triangulation gives at best).
    from reconstruct.solver.rays import viewing_rays

    rays = viewing_rays(problem)
    centers = problem.centers
    depth = np.einsum("fpi,fpi->fp", truth - centers[:, None], rays)
    on_rays = centers[:, None] + depth[..., None] * rays
    result = refine(problem, on_rays, times)
    before = np.sqrt(np.mean(error_mm(on_rays, truth) ** 2))
    after = np.sqrt(np.mean(error_mm(result.points, truth) ** 2))
    assert after < 0.5 * before
    # GCV picked a real amount of smoothing, not the grid's smallest value.
    assert np.all(result.smoothness > SMOOTHNESS_GRID[0])


def test_gcv_skips_smoothness_values_whose_fit_interpolates_its_rays() -> None:
    from reconstruct.trajectory import _least_gcv

    m = np.array([[40.0], [40.0]])
    # Row 0: the two smallest values fit every ray (tr(H) ~ m): RSS ~ 0 over a vanishing denominator gives a tiny,
    # meaningless score; the real minimum is at index 3. Row 1: every value interpolates.
    rss = np.array([[1e-12, 1e-10, 4.0, 3.0, 9.0], [1e-12, 1e-11, 1e-10, 1e-9, 1e-8]])
    trace = np.array([[40.0, 39.99, 20.0, 10.0, 5.0], [40.0, 40.0, 39.99, 39.9, 39.5]])
    chosen = _least_gcv(rss, trace, m)
    score = rss[0] / 40.0 / np.maximum(1 - trace[0] / 40.0, 1e-9) ** 2
    assert int(np.argmin(score)) == 1  # what the plain GCV minimum would have taken
    assert chosen.tolist() == [3, 0]


def test_gcv_on_demand_chooses_as_the_whole_grid() -> None:
    # The fits and traces are computed only where a score may beat the best known one (issue 22): the choice, the
    # RSS and the trace at the choice must be those of the whole grid, for many points.
    from reconstruct.trajectory import _GridFits, _least_gcv, _make_tracks, camera_normalization, viewing_rays

    times, camera_of = round_robin(300, 120.0)
    problem, truth = capture(times, camera_of, noise_px=1.5)
    normalization = camera_normalization(problem.centers, problem.video_index)
    nodes = time_nodes(times)
    focal = np.sqrt(problem.K[:, 0, 0] * problem.K[:, 1, 1])
    start = normalization.apply(start_points(problem, truth))
    tracks = _make_tracks(problem, start, viewing_rays(problem), normalization.apply(problem.centers), focal, nodes)
    prior, n, grid = prior_bands(nodes), len(nodes.times), list(SMOOTHNESS_GRID)
    m = np.array([2.0 * t.seen.size for t in tracks])[:, None]
    whole = _GridFits(tracks, prior, grid, n)
    whole.compute(np.ones(whole.known.shape, dtype=bool))
    lazy = _GridFits(tracks, prior, grid, n)
    lazy.batch = 8  # several batches and rounds, as on long captures
    lazy.least_gcv(m)
    assert not lazy.known.all()
    chosen = _least_gcv(whole.rss, whole.trace, m)
    assert chosen.tolist() == _least_gcv(lazy.rss, np.where(lazy.known, lazy.trace, m), m).tolist()
    rows = np.arange(len(tracks))
    assert np.array_equal(lazy.rss[rows, chosen], whole.rss[rows, chosen])
    assert np.array_equal(lazy.trace[rows, chosen], whole.trace[rows, chosen])


def test_a_false_observation_is_down_weighted() -> None:
    times, camera_of = round_robin(120, 60.0)
    problem, truth = capture(times, camera_of, noise_px=0.5)
    f, p = 60, 1
    problem.uv[f, p] += [80.0, -60.0]  # a false detection 100 px away
    start = start_points(problem, truth, error_mm=5.0)
    robust = refine(problem, start, times, RefineOptions(loss=RobustLoss.CAUCHY))
    plain = refine(problem, start, times, RefineOptions(loss=RobustLoss.NONE))
    assert robust.outliers[f, p]
    assert robust.weights[f, p] < 0.05
    assert robust.outliers.sum() <= 3  # the other observations keep their weight
    assert error_mm(robust.points[f, p], truth[f, p]) < 3.0
    # IRLS with a fixed scale majorizes the robust cost: it never increases within a GCV pass.
    rounds = IRLS_ITERATIONS
    for start_round in range(0, len(robust.cost), rounds):
        costs = np.array(robust.cost[start_round : start_round + rounds])
        assert np.all(np.diff(costs) <= 1e-9 * costs[0])
    assert error_mm(plain.points[f, p], truth[f, p]) > 3 * error_mm(robust.points[f, p], truth[f, p])
    huber = refine(problem, start, times, RefineOptions(loss=RobustLoss.HUBER))
    assert huber.weights[f, p] < 0.2
    assert error_mm(huber.points[f, p], truth[f, p]) < error_mm(plain.points[f, p], truth[f, p])


def test_unobserved_frames_are_interpolated() -> None:
    times, camera_of = round_robin(160, 80.0)
    problem, truth = capture(times, camera_of)
    gap = np.arange(70, 78)
    problem.uv[gap, 2] = np.nan
    start = start_points(problem, truth)
    start[gap, 2] = np.nan  # the input may lack them too
    result = refine(problem, start, times)
    assert np.all(np.isnan(result.weights[gap, 2]))
    assert np.max(error_mm(result.points[gap, 2], truth[gap, 2])) < 5.0
    assert np.median(error_mm(result.points[:, 2], truth[:, 2])) < 1.0


def test_uneven_and_concurrent_times() -> None:
    rng = np.random.default_rng(3)
    instants = np.sort(rng.uniform(0.0, 2.0, 100))
    # Every instant seen by one camera; 20 of them by a second camera at exactly the same time.
    twice = rng.choice(100, size=20, replace=False)
    times = np.concatenate([instants, instants[twice]])
    first = rng.integers(0, 4, 100)
    camera_of = np.concatenate([first, (first[twice] + 2) % 4])
    problem, truth = capture(times, camera_of)
    result = refine(problem, start_points(problem, truth), times)
    errors = error_mm(result.points, truth)
    assert np.median(errors) < 1.0
    assert np.percentile(errors, 95) < 5.0
    # Concurrent frames share one position.
    np.testing.assert_allclose(result.points[twice], result.points[100:], atol=1e-9)
    # The same capture in another frame order gives the same points.
    order = rng.permutation(len(times))
    shuffled, _ = capture(times[order], camera_of[order])
    again = refine(shuffled, start_points(problem, truth)[order], times[order])
    np.testing.assert_allclose(again.points, result.points[order], atol=0.05)


def test_fixed_smoothness_and_cost_history() -> None:
    times, camera_of = round_robin(80, 40.0)
    problem, truth = capture(times, camera_of, noise_px=1.0)
    weak = refine(problem, truth, times, RefineOptions(rule=SmoothnessRule.FIXED, smoothness=1e-6))
    strong = refine(problem, truth, times, RefineOptions(rule=SmoothnessRule.FIXED, smoothness=1e6))
    assert np.all(weak.smoothness == 1e-6)
    # A huge weight flattens the motion into a straight line: far from the truth, larger residuals.
    assert np.nanmedian(strong.residual_px) > 10 * np.nanmedian(weak.residual_px)
    assert len(weak.cost) == IRLS_ITERATIONS * GCV_PASSES
    one = refine(problem, truth, times, RefineOptions(rule=SmoothnessRule.GCV_GLOBAL))
    assert len(set(one.smoothness.tolist())) == 1


def test_bad_inputs_raise_input_errors() -> None:
    times, camera_of = round_robin(20, 30.0)
    problem, truth = capture(times, camera_of)
    with pytest.raises(InputError, match="times have shape"):
        refine(problem, truth, times[:-1])
    with pytest.raises(InputError, match="points have shape"):
        refine(problem, truth[:, :2], times)
    bad = times.copy()
    bad[4] = np.nan
    with pytest.raises(InputError, match=r"frame 4 .* has no global time"):
        refine(problem, truth, bad)


def test_points_the_solver_left_empty_stay_empty() -> None:
    times, camera_of = round_robin(40, 30.0)
    problem, truth = capture(times, camera_of)
    start = truth.copy()
    start[:, 3] = np.nan
    result = refine(problem, start, times)
    assert np.isnan(result.points[:, 3]).all()
    assert np.isnan(result.smoothness[3])
    assert np.median(error_mm(result.points[:, :3], truth[:, :3])) < 1.0


def test_a_long_capture_chooses_its_smoothness_on_the_middle_window(monkeypatch: pytest.MonkeyPatch) -> None:
    times, camera_of = round_robin(600, 120.0)
    problem, truth = capture(times, camera_of, noise_px=1.0)
    start = start_points(problem, truth)
    whole = refine(problem, start, times)
    chosen: list[int] = []
    real = trajectory._choose_smoothness

    def spy(tracks, prior, grid, n, *rest):
        chosen.append(n)
        return real(tracks, prior, grid, n, *rest)

    monkeypatch.setattr(trajectory, "GCV_WINDOW", 240)
    monkeypatch.setattr(trajectory, "_choose_smoothness", spy)
    windowed = refine(problem, start, times)
    assert chosen == [240] * trajectory.GCV_PASSES  # every point has 50+ observations in the window
    steps = np.abs(np.round(2 * np.log10(windowed.smoothness / whole.smoothness)))
    assert np.all(steps <= 1)  # the same grid value, or its neighbour
    before, after = np.median(error_mm(whole.points, truth)), np.median(error_mm(windowed.points, truth))
    assert after < 1.1 * before
    # the error predicted for an unseen ray comes from the window's GCV too (it judges competing clocks)
    assert np.isfinite(windowed.gcv_px2).all() and abs(predicted_px(windowed) / predicted_px(whole) - 1) < 0.2


def test_a_point_seen_too_little_in_the_window_is_chosen_on_all_of_its_instants(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    times, camera_of = round_robin(600, 120.0)
    problem, truth = capture(times, camera_of, noise_px=1.0)
    problem.uv[150:450, 0] = np.nan  # point 0 is unobserved in the middle 300 frames
    start = start_points(problem, truth)
    calls: list[tuple[int, int]] = []
    real = trajectory._choose_smoothness

    def spy(tracks, prior, grid, n, *rest):
        calls.append((len(tracks), n))
        return real(tracks, prior, grid, n, *rest)

    monkeypatch.setattr(trajectory, "GCV_WINDOW", 240)
    monkeypatch.setattr(trajectory, "_choose_smoothness", spy)
    refine(problem, start, times)
    assert calls[:2] == [(3, 240), (1, 600)]


def test_the_predicted_error_is_the_noise_and_compares_only_points_both_refined() -> None:
    times, camera_of = round_robin(300, 120.0)
    problem, truth = capture(times, camera_of, noise_px=1.0)
    result = refine(problem, start_points(problem, truth), times)
    assert 0.8 < predicted_px(result) < 1.4  # per-axis noise of 1 px, predicted for rays the fit did not see
    other = trajectory.RefineResult(**{**vars(result), "gcv_px2": result.gcv_px2 * 4.0})
    other.gcv_px2[0] = np.nan  # point 0 not refined there: left out of both
    pair = predicted_pair(result, other)
    assert pair is not None
    assert pair[1] == pytest.approx(2 * pair[0]) and pair[0] == pytest.approx(np.sqrt(np.median(result.gcv_px2[1:])))
    interpolating = trajectory.RefineResult(**{**vars(result), "gcv_px2": np.full_like(result.gcv_px2, np.inf)})
    assert predicted_pair(interpolating, interpolating) is None  # nothing to compare: the caller uses residuals
    assert predicted_pair(result, interpolating) == (pytest.approx(predicted_px(result)), np.inf)


def test_one_videos_rays_under_a_strong_prior_are_solved() -> None:
    """A point seen on a few frames by one video alone (the held-out fit of a two-camera point, on a real bat
    recording), under GCV's strongest smoothness: straight motions along the rays are pinned by nothing but the
    anchor, and the system's condition passes what a Cholesky holds. The anchor then keeps those directions."""
    n = 1128
    prior = prior_bands(time_nodes(np.arange(n) / 25.0))
    ray = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    blocks = np.zeros((n, 3, 3))
    blocks[500:520] = 2.6e7 * (np.eye(3) - np.outer(ray, ray))  # 20 frames' rays, one direction
    anchor = np.random.default_rng(0).normal(size=(n, 3))
    rhs = np.einsum("nij,nj->ni", blocks, anchor)
    positions, _ = trajectory._fit(prior, 1.0, 1e13, blocks, rhs, anchor)
    assert np.isfinite(positions).all()
    # across the rays the positions meet them (a straight line through the seen frames' anchors, nearly)
    seen = positions[500:520] - anchor[500:520]
    across = seen - np.outer(seen @ ray, ray)
    assert np.abs(across).max() < 2.0
