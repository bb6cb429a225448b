import numpy as np
import pytest

from reconstruct.solver.wstep import WStepOptions, solve_w
from reconstruct.solver.xstep import RayConstraint, XStepOptions, quadratic_form, solve_x


def _setup(F=18, P=3, seed=0, miss=0.3):
    rng = np.random.default_rng(seed)
    video_index = np.sort(rng.integers(0, 3, F))
    centers = rng.normal(size=(F, 3)) * 2
    rays = rng.normal(size=(F, P, 3))
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    rays[rng.random((F, P)) < miss] = np.nan
    shapes = rng.normal(size=(F, 3 * P))
    W, _ = solve_w(shapes, video_index, P, WStepOptions())
    return W.to_csc(), centers, rays, video_index


def _dense_solution(W, centers, rays, video_index, options):
    """Minimize the X-step cost by one dense least-squares solve over explicit unknowns."""
    F, P = rays.shape[:2]
    Q = quadratic_form(W, video_index, P, options.lambda2).toarray()
    # Cost per point: y^T (Q kron I3) y (+ soft terms); build y = y0 + J z densely.
    Q3 = np.kron(Q, np.eye(3))
    out = np.empty((F, P, 3))
    for p in range(P):
        observed = ~np.isnan(rays[:, p, 0])
        if options.constraint is RayConstraint.HARD:
            columns, y0 = [], np.zeros(3 * F)
            for f in range(F):
                if observed[f]:
                    col = np.zeros(3 * F)
                    col[3 * f : 3 * f + 3] = rays[f, p]
                    columns.append(col)
                    y0[3 * f : 3 * f + 3] = centers[f]
                else:
                    for axis in range(3):
                        col = np.zeros(3 * F)
                        col[3 * f + axis] = 1
                        columns.append(col)
            J = np.column_stack(columns)
            z = np.linalg.solve(J.T @ Q3 @ J, -J.T @ Q3 @ y0)
            out[:, p] = (y0 + J @ z).reshape(F, 3)
        else:
            H = Q3.copy()
            rhs = np.zeros(3 * F)
            weight = options.lambda3 / (F * P)
            for f in np.flatnonzero(observed):
                block = weight * (np.eye(3) - np.outer(rays[f, p], rays[f, p]))
                H[3 * f : 3 * f + 3, 3 * f : 3 * f + 3] += block
                rhs[3 * f : 3 * f + 3] = block @ centers[f]
            out[:, p] = np.linalg.solve(H, rhs).reshape(F, 3)
    return out


@pytest.mark.parametrize("constraint", list(RayConstraint))
@pytest.mark.parametrize("lambda2", [0.0, 0.1])
def test_x_step_matches_dense_least_squares(constraint, lambda2):
    W, centers, rays, video_index = _setup()
    options = XStepOptions(lambda2=lambda2, constraint=constraint)
    points = solve_x(W, centers, rays, video_index, options)
    reference = _dense_solution(W, centers, rays, video_index, options)
    np.testing.assert_allclose(points, reference, atol=1e-6 * np.abs(reference).max())


def test_hard_constraint_keeps_observed_points_on_their_rays():
    W, centers, rays, video_index = _setup(seed=3)
    points = solve_x(W, centers, rays, video_index, XStepOptions(constraint=RayConstraint.HARD))
    offset = points - centers[:, None]
    along = np.nansum(offset * rays, axis=-1)
    perpendicular = offset - along[..., None] * np.nan_to_num(rays)
    observed = ~np.isnan(rays[..., 0])
    assert np.abs(perpendicular[observed]).max() < 1e-9


@pytest.mark.parametrize("constraint", list(RayConstraint))
def test_points_split_over_threads_match_dense_least_squares(constraint, monkeypatch):
    import reconstruct.solver.xstep as xstep

    monkeypatch.setattr(xstep, "PARALLEL_SIZE", 0)  # split even this small problem
    W, centers, rays, video_index = _setup(P=5, seed=4)
    options = XStepOptions(lambda2=0.1, constraint=constraint, workers=2)
    start = np.random.default_rng(4).normal(size=rays.shape)
    points = solve_x(W, centers, rays, video_index, options, start=start)
    reference = _dense_solution(W, centers, rays, video_index, options)
    np.testing.assert_allclose(points, reference, atol=1e-6 * np.abs(reference).max())
