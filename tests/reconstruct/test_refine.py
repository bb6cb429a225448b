"""reconstruct.trajectory: smoothing-spline trajectories through viewing rays on known global times."""

from __future__ import annotations

import numpy as np
import pytest

from dynrecon.errors import InputError
from reconstruct import trajectory
from reconstruct.solver.problem import Problem
from reconstruct.trajectory import (
    BANDS,
    GCV_PASSES,
    IRLS_ITERATIONS,
    SMOOTHNESS_GRID,
    RefineOptions,
    RobustLoss,
    SmoothnessRule,
    prior_bands,
    refine,
    refine_with_clocks,
    time_nodes,
)
from simulation.simulate import look_at, project

DISTANCE_MM = 2700.0
K = np.array([[1000.0, 0, 499.5], [0, 1000.0, 499.5], [0, 0, 1.0]])


def trajectories(times: np.ndarray, points: int = 4) -> np.ndarray:
    """(F, P, 3) smooth motion in mm: each point on its own Lissajous path, ~0.5 m across, ~1 Hz."""
    phase = np.arange(points)[None, :]
    t = times[:, None]
    x = 300 * np.sin(2 * np.pi * 0.9 * t + phase)
    y = 200 * np.cos(2 * np.pi * 1.3 * t + 0.5 * phase)
    z = 1000 + 150 * np.sin(2 * np.pi * 0.7 * t + 0.3 * phase) + 100 * phase
    return np.stack([x, y, z], axis=-1)


def capture(
    times: np.ndarray, camera_of: np.ndarray, noise_px: float = 0.0, seed: int = 0, cameras: int = 4
) -> tuple[Problem, np.ndarray]:
    """A Problem seeing `trajectories(times)` with camera camera_of[f] at frame f; returns (problem, truth)."""
    truth = trajectories(times)
    F, P = truth.shape[:2]
    target = np.array([0.0, 0.0, 1000.0])
    up = np.array([0.0, 0.0, 1.0])
    poses = []
    for c in range(cameras):
        angle = 2 * np.pi * c / cameras + 0.3
        poses.append(look_at(target + DISTANCE_MM * np.array([np.cos(angle), np.sin(angle), 0.1]), target, up))
    R = np.stack([poses[c][0] for c in camera_of])
    t = np.stack([poses[c][1] for c in camera_of])
    uv = np.stack([project(truth[f], K, R[f], t[f])[0] for f in range(F)])
    uv += np.random.default_rng(seed).normal(0.0, noise_px, uv.shape)
    frames = np.zeros(F, dtype=np.int64)
    for c in range(cameras):
        frames[camera_of == c] = np.arange(np.sum(camera_of == c))
    problem = Problem(
        video_names=[f"cam{c}" for c in range(cameras)],
        video_index=np.asarray(camera_of),
        frames=frames,
        times=times.copy(),
        point_names=[f"p{i}" for i in range(P)],
        K=np.repeat(K[None], F, axis=0),
        R=R,
        t=t,
        dist=[None] * F,
        uv=uv,
    )
    return problem, truth


def round_robin(count: int, rate_hz: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Captures at `rate_hz` overall, each by one camera, never the same camera twice in a row."""
    rng = np.random.default_rng(seed)
    camera_of = np.zeros(count, dtype=np.int64)
    for k in range(1, count):
        camera_of[k] = (camera_of[k - 1] + rng.integers(1, 4)) % 4
    return np.arange(count) / rate_hz, camera_of


def start_points(problem: Problem, truth: np.ndarray, seed: int = 1, error_mm: float = 30.0) -> np.ndarray:
    """A poor start: the truth displaced by `error_mm` Gaussian noise per coordinate."""
    return truth + np.random.default_rng(seed).normal(0.0, error_mm, truth.shape)


def error_mm(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(estimate - truth, axis=-1)


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


def test_nearly_concurrent_times_merge_into_one_instant() -> None:
    nodes = time_nodes(np.array([0.0, 0.1, 0.1 + 1e-6, 0.2, 0.3]), merge_fraction=0.01)
    assert len(nodes.times) == 4
    assert nodes.node_of_frame[1] == nodes.node_of_frame[2]
    assert nodes.tau == pytest.approx(0.1, rel=1e-4)


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


def test_prior_is_the_second_difference_on_uniform_times() -> None:
    nodes = time_nodes(np.arange(6) * 0.25, merge_fraction=0.01)
    bands = prior_bands(nodes)
    n = 6
    D = np.zeros((n - 2, n))
    for i in range(n - 2):
        D[i, i : i + 3] = [1.0, -2.0, 1.0]
    expected = np.kron(D.T @ D, np.eye(3))
    dense = np.zeros((3 * n, 3 * n))
    for d in range(BANDS):
        idx = np.arange(3 * n - d)
        dense[idx + d, idx] = bands[d, : 3 * n - d]
        dense[idx, idx + d] = bands[d, : 3 * n - d]
    np.testing.assert_allclose(dense, expected, atol=1e-12)


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


def test_clock_refinement_recovers_offset_and_rate_errors() -> None:
    times, camera_of = round_robin(160, 60.0)
    problem, truth = capture(times, camera_of)
    # Estimated clocks off by a fraction of a frame: camera 2 late by 6 ms, camera 3 running 1 % fast.
    wrong = times.copy()
    wrong[camera_of == 2] += 0.006
    middle = np.median(times[camera_of == 3])
    wrong[camera_of == 3] += 0.01 * (times[camera_of == 3] - middle)
    start = start_points(problem, truth, error_mm=5.0)
    plain = refine(problem, start, wrong)
    fixed = refine_with_clocks(problem, start, wrong, reference=0)
    correction = fixed.correction
    assert correction.offset[0] == pytest.approx(0.0, abs=1e-12) and correction.rate[0] == pytest.approx(0.0, abs=1e-12)
    # Every frame's time back within 1 ms of the truth (the gauge is video 0's clock, which was right).
    assert np.max(np.abs(fixed.times - times)) < 1e-3
    assert fixed.cost[-1] < fixed.cost[0]
    before = np.median(error_mm(plain.points, truth))
    after = np.median(error_mm(fixed.result.points, truth))
    assert after < 0.5 * before


def test_clock_refinement_result_is_the_refinement_at_its_times() -> None:
    # The rounds reuse refinements they already computed (same inputs): the result is still bitwise the one of a
    # fresh refinement at the polished times.
    times, camera_of = round_robin(120, 60.0, seed=3)
    problem, truth = capture(times, camera_of, noise_px=0.5)
    wrong = times.copy()
    wrong[camera_of == 1] += 0.004
    start = start_points(problem, truth, error_mm=5.0)
    fixed = refine_with_clocks(problem, start, wrong, reference=0)
    again = refine(problem, start, fixed.times)
    np.testing.assert_array_equal(fixed.result.points, again.points)
    np.testing.assert_array_equal(fixed.result.smoothness, again.smoothness)
    # and the refinement at the input times, which a rejected polish falls back to
    assert fixed.at_input is not None
    np.testing.assert_array_equal(fixed.at_input.points, refine(problem, start, wrong).points)


def test_worker_threads_change_no_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    # The points are independent: split among threads (their banded systems side by side in fewer or more LAPACK
    # calls), the refinement, the polish cost and so the polished clocks are bitwise those of one thread. Merged
    # instants (two frames at one time) take `_sum_at_slots`'s bincount path.
    times, camera_of = round_robin(150, 60.0, seed=5)
    times[[40, 90]] = times[[39, 89]]
    problem, truth = capture(times, camera_of, noise_px=0.5)
    wrong = times.copy()
    wrong[camera_of == 1] += 0.003
    start = start_points(problem, truth, error_mm=5.0)
    results = {}
    for workers in (1, 3):
        monkeypatch.setattr(trajectory, "WORKERS", workers)
        results[workers] = refine_with_clocks(problem, start, wrong, reference=0)
    one, many = results[1], results[3]
    np.testing.assert_array_equal(one.times, many.times)
    np.testing.assert_array_equal(one.result.points, many.result.points)
    np.testing.assert_array_equal(one.result.weights, many.result.weights)
    np.testing.assert_array_equal(one.result.smoothness, many.result.smoothness)
    assert one.cost == many.cost


def test_sums_at_slots_are_bincount_sums() -> None:
    rng = np.random.default_rng(0)
    index = rng.integers(0, 50, 200)
    values = rng.normal(size=(200, 3))
    values[:5] = -0.0
    alone = np.bincount(index, minlength=50)[index] == 1
    padded = np.concatenate([values, np.zeros((1, 3))])
    fast = trajectory._sum_at_slots(index, padded, 50, alone)
    assert fast.tobytes() == trajectory._sum_at(index, values, 50).tobytes()


@pytest.mark.parametrize("minimum", [0.0, 0.0004, 0.3, -0.7])
def test_the_clock_search_from_zero_costs_two_solves_where_the_clock_is_right(minimum):
    calls: list[float] = []

    def cost(x: float) -> float:
        calls.append(x)
        return (x - minimum) ** 2

    reach, tolerance = 1.0, 0.005
    best, value = trajectory._search_from_zero(cost, cost(0.0), reach, tolerance)
    steps = len(calls) - 1  # f(0) is known to the caller: not a search step
    assert abs(best - minimum) <= tolerance and value == (best - minimum) ** 2
    if abs(minimum) <= tolerance / 2:
        assert steps == 2 and best == 0.0  # the two probes: the minimum lies between them
    else:  # the golden-section search on the lower side, as many steps as before on half the bracket
        assert np.sign(best) == np.sign(minimum)
        _, golden_value = trajectory._golden_search(lambda x: (x - minimum) ** 2, -reach, reach, tolerance)
        assert value <= golden_value + tolerance**2


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


def test_a_large_capture_polishes_its_clocks_on_its_most_observed_points(monkeypatch: pytest.MonkeyPatch) -> None:
    observed = np.ones((10, 5), dtype=bool)
    observed[:4, 1] = observed[:7, 3] = False
    refined = np.array([True, True, True, True, False])
    monkeypatch.setattr(trajectory, "POLISH_SIZE", 20)  # two points of 10 frames
    monkeypatch.setattr(trajectory, "POLISH_MIN_POINTS", 2)
    assert trajectory._polish_points(observed, refined).tolist() == [True, False, True, False, False]
    monkeypatch.setattr(trajectory, "POLISH_SIZE", 10_000)
    assert np.array_equal(trajectory._polish_points(observed, refined), refined)

    # the clocks come back from two of the four points as from all of them
    times, camera_of = round_robin(160, 60.0)
    problem, truth = capture(times, camera_of)
    wrong = times.copy()
    wrong[camera_of == 2] += 0.006
    start = start_points(problem, truth, error_mm=5.0)
    monkeypatch.setattr(trajectory, "POLISH_SIZE", 2 * 160)
    fixed = refine_with_clocks(problem, start, wrong, reference=0)
    assert np.max(np.abs(fixed.times - times)) < 1e-3
    assert np.all(np.isfinite(fixed.result.points[:, :, 0]))  # every point refined on the polished clocks
