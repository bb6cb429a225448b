from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import minimize

from reconstruct.solver.wstep import WStepOptions, objective_full, solve_w


def _shapes(F=24, P=4, videos=3, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 2, F))
    base = rng.normal(size=(P, 3))
    shapes = base[None] + 0.3 * np.sin(3 * t[:, None, None] + rng.normal(size=(P, 3))[None])
    shapes += rng.normal(scale=0.01, size=shapes.shape)
    video_index = rng.integers(0, videos, F)
    return shapes.reshape(F, -1), video_index, P


def _kkt_residual(shapes, video_index, P, W, lambda1):
    """Largest violation of the KKT conditions of the full W-step, in gradient units relative to its scale."""
    F = len(shapes)
    grad = 2.0 / (F * P) * (shapes @ (W.T @ shapes - shapes).T) + 4.0 * lambda1 / F * (W - W.T)
    allowed = video_index[:, None] != video_index[None, :]
    worst = 0.0
    for f in range(F):
        g = grad[allowed[:, f], f]
        w = W[allowed[:, f], f]
        mu = g[w > 1e-9].mean()
        worst = max(worst, np.abs(g[w > 1e-9] - mu).max(), max(0.0, mu - g.min()))
    return worst / np.abs(grad).max()


@pytest.mark.parametrize("lambda1", [0.0, 0.05, 1.0])
def test_w_step_satisfies_kkt_on_the_full_problem(lambda1):
    shapes, video_index, P = _shapes()
    # Exact W-steps: the default stall guard keeps PDAS's best iterate once it gains little (within ~0.1 % of g,
    # not within 1e-4 of KKT).
    options = WStepOptions.exact(lambda1=lambda1, nearest=3)
    W, stats = solve_w(shapes, video_index, P, options)
    dense = W.to_csc().toarray()
    assert stats.converged
    np.testing.assert_allclose(dense.sum(axis=0), 1.0, atol=1e-9)
    assert dense.min() >= -1e-12
    assert np.all(np.diag(dense) == 0)
    assert np.all(dense[video_index[:, None] == video_index[None, :]] == 0)
    assert _kkt_residual(shapes, video_index, P, dense, lambda1) < 1e-4


def test_w_step_matches_a_general_qp_solver():
    shapes, video_index, P = _shapes(F=14, P=3, seed=1)
    F = len(shapes)
    lambda1 = 0.05
    W, _ = solve_w(shapes, video_index, P, WStepOptions(lambda1=lambda1, kkt_tolerance=1e-9, max_rounds=20))
    ours = objective_full(shapes, W.to_csc(), lambda1, P)
    allowed = video_index[:, None] != video_index[None, :]
    rows, cols = np.nonzero(allowed)

    def unpack(x):
        dense = np.zeros((F, F))
        dense[rows, cols] = x
        return dense

    def cost(x):
        dense = unpack(x)
        residual = shapes - dense.T @ shapes
        return np.sum(residual**2) / (F * P) + lambda1 / F * np.sum((dense - dense.T) ** 2)

    constraints = [{"type": "eq", "fun": lambda x, f=f: unpack(x)[:, f].sum() - 1.0} for f in range(F)]
    x0 = np.concatenate([np.full(allowed[:, f].sum(), 1.0 / allowed[:, f].sum()) for f in range(F)])
    x0 = unpack(x0)[rows, cols]
    reference = minimize(
        cost,
        x0,
        method="SLSQP",
        bounds=[(0, 1)] * len(rows),
        constraints=constraints,
        options={"maxiter": 1000, "ftol": 1e-14},
    )
    assert ours <= reference.fun * (1 + 1e-6) + 1e-12


def test_warm_start_reuses_previous_solution():
    shapes, video_index, P = _shapes(seed=2)
    # Exact W-steps: no early stop of a stalling PDAS, so that both solves reach the same optimum.
    options = WStepOptions(kkt_tolerance=1e-9, max_rounds=20, stall_iterations=10**6)
    W, cold = solve_w(shapes, video_index, P, options)
    W2, warm = solve_w(shapes, video_index, P, options, previous=W)
    assert warm.iterations <= cold.iterations
    np.testing.assert_allclose(W2.to_csc().toarray(), W.to_csc().toarray(), atol=1e-6)


def test_primal_active_set_descends_to_the_working_set_optimum():
    """The fallback that finishes when PDAS cycles: monotone from any feasible start, and exact when its budget
    suffices (same optimum as PDAS on the same working set)."""
    from reconstruct.solver.active_set import FreeSetSolver, WorkingSetProblem, active_set, primal_active_set
    from reconstruct.solver.wstep import WStepStats, _pack_pairs, nearest_other_video

    shapes, video_index, P = _shapes(F=30, seed=3)
    F = len(shapes)
    near = nearest_other_video(shapes, video_index, 6)
    cand, valid = _pack_pairs(near.ravel(), np.repeat(np.arange(F), near.shape[1]), F)
    problem = WorkingSetProblem(shapes, cand, valid, 0.05, P)
    start = problem.project(np.where(valid, 1.0, 0.0))  # uniform weights: feasible, far from optimal
    options = WStepOptions(max_primal_iterations=2)
    short = primal_active_set(problem, FreeSetSolver(problem), start, options, WStepStats())
    assert problem.objective(short) <= problem.objective(start)
    exact = primal_active_set(
        problem, FreeSetSolver(problem), start, WStepOptions(max_primal_iterations=500), WStepStats()
    )
    reference = active_set(problem, start, WStepOptions(), WStepStats())
    assert reference is not None
    assert problem.objective(exact) <= problem.objective(short)
    np.testing.assert_allclose(problem.objective(exact), problem.objective(reference), rtol=1e-9)
    np.testing.assert_allclose(exact.sum(axis=1), 1.0)
    assert exact.min() >= 0


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_local_inner_equals_the_gathered_products(workers, monkeypatch):
    import reconstruct.solver.wstep as wstep
    from reconstruct.solver.wstep import local_inner, nearest_in_pool

    monkeypatch.setattr(wstep, "PARALLEL_ROWS", 0)  # threads split the rows even at this size

    rng = np.random.default_rng(4)
    A, B = rng.normal(size=(150, 7)), rng.normal(size=(150, 7))
    index = np.clip(np.arange(150)[:, None] + rng.integers(-20, 21, size=(150, 9)), -1, 149)
    index[rng.random(index.shape) < 0.2] = -1
    expected = np.where(index >= 0, np.einsum("fd,fcd->fc", A, B[np.maximum(index, 0)]), 0.0)
    serial = local_inner(A, B, index, chunk=16)
    np.testing.assert_allclose(serial, expected, atol=1e-12)
    np.testing.assert_array_equal(local_inner(A, B, index, chunk=16, workers=workers), serial)  # to the bit
    nearest = nearest_in_pool(A, index, 3, workers)
    for f in (0, 70, 149):
        candidates = index[f][index[f] >= 0]
        order = candidates[np.argsort(np.linalg.norm(A[candidates] - A[f], axis=1))][:3]
        np.testing.assert_array_equal(nearest[f][: len(order)], order)


def test_smallest_per_row_equals_a_full_sort():
    from reconstruct.solver.wstep import smallest_per_row

    rng = np.random.default_rng(7)
    values = rng.normal(size=(40, 30))
    values[3, 2:] = np.inf  # fewer finite values than k
    index, picked = smallest_per_row(values.copy(), 5)
    expected = np.argsort(values, axis=1, kind="stable")[:, :5]
    finite = np.isfinite(np.take_along_axis(values, expected, axis=1))
    np.testing.assert_array_equal(index[finite], expected[finite])
    np.testing.assert_array_equal(picked[finite], np.take_along_axis(values, index, axis=1)[finite])
    assert np.all(np.diff(picked[finite.all(axis=1)], axis=1) >= 0)
    assert not np.isfinite(picked[3, 2:]).any()


def test_seed_pairs_are_limited_per_frame_keeping_the_nearest_ranks():
    from reconstruct.solver.wstep import _limit_seeds_per_frame

    rows = np.array([5, 5, 5, 5, 2, 5, 2])  # frame 5 is a seed of 5 columns, frame 2 of two
    cols = np.array([0, 1, 3, 4, 6, 7, 8])
    rank = np.array([3, 0, 1, 2, 0, 0, 5])
    kept_rows, kept_cols = _limit_seeds_per_frame(rows, cols, rank, 3)
    assert sorted(zip(kept_rows.tolist(), kept_cols.tolist(), strict=True)) == [(2, 6), (2, 8), (5, 1), (5, 3), (5, 7)]


def _windowed_problem(seed):
    """A working set with a window pool (several independent components of columns), its shapes and the random
    generator that drew them (for a random free set)."""
    from reconstruct.solver.active_set import WorkingSetProblem
    from reconstruct.solver.wstep import _pack_pairs, nearest_in_pool

    rng = np.random.default_rng(seed)
    F, V = 90, 3
    shapes = np.cumsum(rng.normal(size=(F, 6)), axis=0)
    video_index = np.arange(F) % V
    frames = np.arange(F)
    pool = frames[:, None] + np.array([-4, -2, -1, 1, 2, 4])[None, :]
    pool[(pool < 0) | (pool >= F) | (video_index[np.clip(pool, 0, F - 1)] == video_index[:, None])] = -1
    near = nearest_in_pool(shapes, pool, 3)
    keep = near >= 0
    cand, valid = _pack_pairs(near[keep], np.broadcast_to(frames[:, None], near.shape)[keep], F)
    return WorkingSetProblem(shapes, cand, valid, 0.05, 2), shapes, rng


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kkt_re_solves_only_changed_components_and_equals_a_fresh_solve(seed, workers, monkeypatch):
    import reconstruct.solver.active_set as working_set
    from reconstruct.solver.active_set import FreeSetSolver

    monkeypatch.setattr(working_set, "PARALLEL_KKT", 0)  # with 2 workers, components are split over threads
    problem, _, rng = _windowed_problem(seed)
    valid = problem.valid.ravel()
    free = valid & (rng.random(valid.shape) < 0.6)
    solver = FreeSetSolver(problem, workers)
    solver.ensure_nonempty_columns(free, np.zeros(len(free)))
    solver.solve(free)
    # Change a few entries, some of which make or break partner links.
    flip = rng.choice(np.flatnonzero(valid), 6, replace=False)
    changed = free.copy()
    changed[flip] = ~changed[flip]
    solver.ensure_nonempty_columns(changed, np.zeros(len(free)))
    cached = solver.solve(changed)
    fresh = FreeSetSolver(problem).solve(changed)
    assert cached is not None and fresh is not None
    np.testing.assert_allclose(cached[0], fresh[0], atol=1e-10)
    np.testing.assert_allclose(cached[1], fresh[1], rtol=1e-8, atol=1e-14)


@pytest.mark.parametrize("workers", [1, 2])
def test_column_grams_equal_the_padded_products(workers, monkeypatch):
    import scipy.linalg

    import reconstruct.solver.active_set as working_set
    from reconstruct.solver.active_set import column_grams

    monkeypatch.setattr(working_set, "PARALLEL_GRAMS", 0)  # with 2 workers, the columns are split over threads

    problem, shapes, _ = _windowed_problem(3)
    gram, lam_max = column_grams(shapes, problem.cand, problem.valid, workers)
    B = np.where(problem.valid[..., None], shapes[problem.cand] - shapes[:, None, :], 0.0)
    expected = np.einsum("fkd,fld->fkl", B, B)
    assert len(np.unique(problem.valid.sum(axis=1))) > 1  # columns of several sizes: blocks of several sizes
    np.testing.assert_allclose(gram.toarray(), scipy.linalg.block_diag(*expected), atol=1e-10)
    assert gram.nnz == int(np.sum(problem.valid.sum(axis=1) ** 2))  # the blocks only, no padding
    np.testing.assert_allclose(lam_max, np.linalg.eigvalsh(expected)[:, -1], rtol=1e-10, atol=1e-12)


def test_column_grams_refuse_a_working_set_that_is_not_packed():
    from reconstruct.solver.active_set import column_grams

    problem, shapes, _ = _windowed_problem(4)
    valid = problem.valid.copy()
    row = int(np.flatnonzero(valid.sum(axis=1) >= 2)[0])
    valid[row, 0] = False  # a hole before the column's last entry
    with pytest.raises(ValueError, match="not packed"):
        column_grams(shapes, problem.cand, valid)


def test_limit_changes_makes_one_change_in_restricted_columns_only():
    from reconstruct.solver.active_set import limit_changes

    F, K = 3, 4
    free = np.array([[1, 1, 1, 0], [1, 1, 0, 0], [1, 0, 0, 0]], dtype=bool).ravel()
    # Column 0 drops two entries and gains one, column 1 gains two, column 2 (unrestricted) gains two.
    proposal = np.array([[1, 0, 0, 1], [1, 1, 1, 1], [1, 1, 1, 0]], dtype=bool).ravel()
    v = np.array([[0.9, -0.2, -0.5, 0.0], [0.5, 0.5, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]).ravel()
    violation = np.array([[0.0, 0.0, 0.0, 0.3], [0.0, 0.0, 0.1, 0.4], [0.0, 0.2, 0.1, 0.0]]).ravel()
    restricted = np.array([True, True, False])
    out = limit_changes(free, proposal, v, violation, restricted, F, K).reshape(F, K)
    np.testing.assert_array_equal(out[0], [1, 1, 0, 0])  # only the most negative entry leaves, nothing enters
    np.testing.assert_array_equal(out[1], [1, 1, 0, 1])  # only the most violating entry enters
    np.testing.assert_array_equal(out[2], proposal.reshape(F, K)[2])


def test_active_set_settles_columns_that_would_wander():
    """Restricting columns that keep changing makes the W-step reach the same optimum (up to degenerate ties)."""
    shapes, video_index, P = _shapes(F=60, P=3, videos=4, seed=5)
    options = WStepOptions(kkt_tolerance=1e-9, max_rounds=20, stall_iterations=10**6, max_active_set_iterations=500)
    plain = solve_w(shapes, video_index, P, replace(options, cycle_changes=10**6))[1]
    limited = solve_w(shapes, video_index, P, replace(options, cycle_changes=1))[1]
    assert plain.converged and limited.converged
    np.testing.assert_allclose(limited.objective, plain.objective, rtol=1e-4)


@pytest.mark.parametrize("seed", [0, 1])
def test_projected_objective_from_h_v_equals_the_objective(seed):
    from reconstruct.solver.active_set import FreeSetSolver

    problem, _, rng = _windowed_problem(seed)
    solver = FreeSetSolver(problem)
    F, K = problem.cand.shape
    # An active-set iterate: on each column's simplex but with a few negative entries, zero outside the set.
    v = np.where(problem.valid, rng.uniform(0.0, 1.0, (F, K)), 0.0)
    v /= v.sum(axis=1, keepdims=True)
    rows = rng.choice(F, 10, replace=False)
    v[rows, 0] -= 0.3
    v[rows, problem.valid[rows].sum(axis=1) - 1] += 0.3
    v = v.ravel()
    projected = problem.project(v.reshape(F, K))
    assert np.any(projected.ravel() != v)
    hv = solver.H @ v
    np.testing.assert_allclose(solver.projected_objective(v, hv, projected), problem.objective(projected), rtol=1e-12)
    np.testing.assert_allclose(
        solver.projected_objective(v, hv, v.reshape(F, K)), problem.objective(v.reshape(F, K)), rtol=1e-12
    )
