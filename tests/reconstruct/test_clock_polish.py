"""reconstruct.clock_polish: per-video clock corrections that minimize the refinement's cost."""

from __future__ import annotations

import numpy as np
import pytest
from refine_capture import capture, error_mm, round_robin, start_points

from reconstruct import clock_polish, trajectory
from reconstruct.clock_polish import refine_with_clocks
from reconstruct.trajectory import refine


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
    # instants (two frames at one time) take `sum_at_slots`'s bincount path.
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


@pytest.mark.parametrize("minimum", [0.0, 0.0004, 0.3, -0.7])
def test_the_clock_search_from_zero_costs_two_solves_where_the_clock_is_right(minimum):
    calls: list[float] = []

    def cost(x: float) -> float:
        calls.append(x)
        return (x - minimum) ** 2

    reach, tolerance = 1.0, 0.005
    best, value = clock_polish._search_from_zero(cost, cost(0.0), reach, tolerance)
    steps = len(calls) - 1  # f(0) is known to the caller: not a search step
    assert abs(best - minimum) <= tolerance and value == (best - minimum) ** 2
    if abs(minimum) <= tolerance / 2:
        assert steps == 2 and best == 0.0  # the two probes: the minimum lies between them
    else:  # the golden-section search on the lower side, as many steps as before on half the bracket
        assert np.sign(best) == np.sign(minimum)
        _, golden_value = clock_polish._golden_search(lambda x: (x - minimum) ** 2, -reach, reach, tolerance)
        assert value <= golden_value + tolerance**2


def test_a_large_capture_polishes_its_clocks_on_its_most_observed_points(monkeypatch: pytest.MonkeyPatch) -> None:
    observed = np.ones((10, 5), dtype=bool)
    observed[:4, 1] = observed[:7, 3] = False
    refined = np.array([True, True, True, True, False])
    monkeypatch.setattr(clock_polish, "POLISH_SIZE", 20)  # two points of 10 frames
    monkeypatch.setattr(clock_polish, "POLISH_MIN_POINTS", 2)
    assert clock_polish._polish_points(observed, refined).tolist() == [True, False, True, False, False]
    monkeypatch.setattr(clock_polish, "POLISH_SIZE", 10_000)
    assert np.array_equal(clock_polish._polish_points(observed, refined), refined)

    # the clocks come back from two of the four points as from all of them
    times, camera_of = round_robin(160, 60.0)
    problem, truth = capture(times, camera_of)
    wrong = times.copy()
    wrong[camera_of == 2] += 0.006
    start = start_points(problem, truth, error_mm=5.0)
    monkeypatch.setattr(clock_polish, "POLISH_SIZE", 2 * 160)
    fixed = refine_with_clocks(problem, start, wrong, reference=0)
    assert np.max(np.abs(fixed.times - times)) < 1e-3
    assert np.all(np.isfinite(fixed.result.points[:, :, 0]))  # every point refined on the polished clocks


def test_times_whose_system_is_singular_cost_infinity_not_a_traceback(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the office corners (seed path forced) some searched clock left a point's banded system numerically not
    positive definite and LAPACK's error ended the solve; such times are no candidate."""
    from scipy.linalg import LinAlgError

    times, camera_of = round_robin(120, 60.0, seed=3)
    problem, truth = capture(times, camera_of, noise_px=0.5)
    wrong = times.copy()
    wrong[camera_of == 1] += 0.004
    start = start_points(problem, truth, error_mm=5.0)
    real = clock_polish.cholesky_banded
    calls = {"n": 0}

    def sometimes_singular(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] % 3 == 0:
            raise LinAlgError("2-th leading minor not positive definite")
        return real(*args, **kwargs)

    monkeypatch.setattr(clock_polish, "cholesky_banded", sometimes_singular)
    fixed = refine_with_clocks(problem, start, wrong, reference=0)
    assert calls["n"] > 3 and np.isfinite(fixed.result.points).all() and np.isfinite(fixed.cost).all()
    assert np.max(np.abs(fixed.times - times)) < 0.01  # a third of the candidates knocked out: a coarser clock
