import numpy as np
import pytest
import scipy.sparse as sp

from reconstruct.wstep import WStepOptions, solve_w
from reconstruct.xstep import RayConstraint, XStepOptions, quadratic_form, solve_x


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
                    col[3 * f:3 * f + 3] = rays[f, p]
                    columns.append(col)
                    y0[3 * f:3 * f + 3] = centers[f]
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
                H[3 * f:3 * f + 3, 3 * f:3 * f + 3] += block
                rhs[3 * f:3 * f + 3] = block @ centers[f]
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


def _missing_run_setup(F=60, P=4, seed=5):
    """A longer capture where one point misses a run of frames and others miss scattered frames."""
    W, centers, rays, video_index = _setup(F=F, P=P, seed=seed, miss=0.15)
    rays[10:25, 0] = np.nan
    return W, centers, rays, video_index


@pytest.mark.parametrize("constraint", list(RayConstraint))
@pytest.mark.parametrize("lambda2", [0.0, 0.1])
def test_factored_path_matches_dense_least_squares(constraint, lambda2):
    """factor_threshold = 0 sends every point to its weak-subspace factorization (soft: two-level CG, hard: direct
    solve), including frames where the point is missing (three free coordinates in the subspace)."""
    W, centers, rays, video_index = _missing_run_setup()
    options = XStepOptions(lambda2=lambda2, constraint=constraint, factor_threshold=0)
    points = solve_x(W, centers, rays, video_index, options)
    reference = _dense_solution(W, centers, rays, video_index, options)
    np.testing.assert_allclose(points, reference, atol=1e-6 * np.abs(reference).max())


def _camera_scene(F=400, P=3, seed=4, opposite=0.95, mutual=False):
    """Four cameras on a circle (two opposite pairs) film P points moving smoothly, one capture per time step in
    turn; W expresses each frame by linear interpolation of the two frames of every other video around its time,
    and gives the opposite camera's pair the share `opposite` of the column (real W-steps often lean on one
    video). `mutual`: the opposite camera's share goes to one frame only, two captures apart, and that frame's to
    this one (frames that express each other, as the W-step's mutual best matches do)."""
    rng = np.random.default_rng(seed)
    cameras = 4
    t = np.arange(F)
    camera = t % cameras
    video_index = np.argsort(np.argsort(camera * F + t, kind="stable"))  # flat position of capture t
    order = np.argsort(video_index)  # capture shown by each flat frame
    angles = 2 * np.pi * np.arange(cameras) / cameras
    ring = 3.0 * np.column_stack([np.cos(angles), np.sin(angles), np.zeros(cameras)])
    phase = rng.uniform(0, 2 * np.pi, (P, 3))
    truth = 0.3 * np.sin(0.02 * t[:, None, None] * (1 + np.arange(3)) + phase[None])  # (F, P, 3)
    centers = ring[camera[order]]
    rays = truth[order] - centers[:, None]
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    rows, cols, vals = [], [], []
    for f in range(F):
        capture = order[f]
        for c in range(cameras):
            if c == camera[capture]:
                continue
            before = capture - (capture - c) % cameras
            after = before + cameras
            share = (capture - before) / cameras
            neighbours = ((before, 1 - share), (after, share))
            if mutual and (c - camera[capture]) % 4 == 2:
                neighbours = ((capture + 2 if capture % 4 < 2 else capture - 2, 1.0),)
            for neighbour, weight in neighbours:
                if 0 <= neighbour < F:
                    rows.append(video_index[neighbour])
                    cols.append(f)
                    vals.append(weight * (opposite if (c - camera[capture]) % 4 == 2 else 1 - opposite))
    W = sp.csc_matrix((vals, (rows, cols)), shape=(F, F))
    W = sp.csc_matrix(W @ sp.diags(1 / np.asarray(W.sum(axis=0)).ravel()))
    return W, centers, rays, np.sort(camera)


@pytest.mark.parametrize("gaps", [False, True])
def test_two_level_preconditioner_needs_few_iterations(monkeypatch, gaps):
    """Opposite cameras leave along-ray motions that Q barely penalizes: block Jacobi needs many CG iterations,
    the weak-subspace preconditioner a handful (the property that keeps the X-step linear in F), also when points
    miss runs of frames (their three free coordinates are in the subspace)."""
    import reconstruct.xstep as xstep

    W, centers, rays, video_index = _camera_scene(P=4)
    if gaps:
        rays[50:90, 1] = np.nan
        rays[200:203, 2] = np.nan
    iterations = {}
    original = xstep._BatchedCG.run

    def counting_run(self, n):
        before = self.iterations
        original(self, n)
        name = self.precondition.__qualname__.split(".")[0]
        iterations[name] = iterations.get(name, 0) + self.iterations - before

    monkeypatch.setattr(xstep._BatchedCG, "run", counting_run)
    options = XStepOptions(lambda2=0.0, factor_threshold=0)
    factored = solve_x(W, centers, rays, video_index, options)
    jacobi = solve_x(W, centers, rays, video_index, XStepOptions(lambda2=0.0, factor_threshold=1e9))
    assert iterations["_soft_two_level"] <= 9
    assert iterations["_soft_jacobi"] >= 40
    reference = _dense_solution(W, centers, rays, video_index, options)
    scale = np.abs(reference).max()
    # Same residual tolerance, but the well-conditioned two-level system leaves a far smaller error.
    assert np.abs(factored - reference).max() < 1e-5 * scale
    assert np.abs(factored - reference).max() < np.abs(jacobi - reference).max()


def test_pair_blocks_speed_up_the_jacobi_cg(monkeypatch):
    """Frames that express each other from opposite cameras form 2x2 along-ray blocks in the first-phase
    preconditioner; without them the block Jacobi CG needs several times more iterations. Same answer."""
    import reconstruct.xstep as xstep

    W, centers, rays, video_index = _camera_scene(mutual=True)
    partner, _ = xstep._mutual_partners(xstep.quadratic_form(W, video_index, 3, 0.0))
    assert np.mean(partner != np.arange(len(partner))) > 0.9
    counts = []
    original = xstep._BatchedCG.run

    def counting_run(self, n):
        before = self.iterations
        original(self, n)
        counts[-1] += self.iterations - before

    monkeypatch.setattr(xstep._BatchedCG, "run", counting_run)
    options = XStepOptions(lambda2=0.0, factor_threshold=1e9)
    counts.append(0)
    paired = solve_x(W, centers, rays, video_index, options)
    monkeypatch.setattr(xstep, "_mutual_partners", lambda Q: (np.arange(Q.shape[0]), np.zeros(Q.shape[0])))
    counts.append(0)
    solve_x(W, centers, rays, video_index, options)
    assert 3 * counts[0] < counts[1]
    reference = _dense_solution(W, centers, rays, video_index, options)
    assert np.abs(paired - reference).max() < 1e-5 * np.abs(reference).max()


@pytest.mark.parametrize("constraint", list(RayConstraint))
def test_slow_points_switch_to_factorization(monkeypatch, constraint):
    """With the default threshold the slow points of a hard problem leave the Jacobi CG after a few checks and are
    factored (soft: two-level CG, hard: direct solve), here with a gap in one point's track."""
    import reconstruct.xstep as xstep

    W, centers, rays, video_index = _camera_scene(P=4)
    rays[50:90, 1] = np.nan
    factored = []
    original = xstep._weak_subspaces

    def recording(Q, r, observed, points):
        factored.extend(points.tolist())
        return original(Q, r, observed, points)

    monkeypatch.setattr(xstep, "_weak_subspaces", recording)
    options = XStepOptions(lambda2=0.0, constraint=constraint)
    points = solve_x(W, centers, rays, video_index, options)
    assert factored
    reference = _dense_solution(W, centers, rays, video_index, options)
    assert np.abs(points - reference).max() < 1e-5 * np.abs(reference).max()
