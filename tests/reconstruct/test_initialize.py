import numpy as np
from synthetic_motion import synthetic_problem

from reconstruct.initialize import closest_ray_points, fill_missing_points, initialize_depths
from reconstruct.rays import camera_normalization, viewing_rays


def test_closest_points_of_two_rays():
    rng = np.random.default_rng(0)
    for _ in range(20):
        ca, cb = rng.normal(size=3), rng.normal(size=3)
        ra, rb = rng.normal(size=3), rng.normal(size=3)
        ra, rb = ra / np.linalg.norm(ra), rb / np.linalg.norm(rb)
        da, db, gap = closest_ray_points(ca, ra, cb, rb)
        # Brute force: least squares over (da, db) of |ca + da ra - cb - db rb|^2.
        A = np.column_stack([ra, -rb])
        (sa, sb), *_ = np.linalg.lstsq(A, cb - ca, rcond=None)
        assert np.allclose([da, db], [sa, sb])
        assert np.isclose(gap, np.sum((ca + sa * ra - cb - sb * rb) ** 2))


def test_parallel_rays_have_no_intersection():
    da, db, gap = closest_ray_points(np.zeros(3), np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))
    assert np.isnan(da) and np.isnan(db) and np.isnan(gap)


def _brute_force_partners(centers, rays, video_index):
    F = len(centers)
    partners = np.full(F, -1)
    for f in range(F):
        best = np.inf
        for j in range(F):
            if video_index[j] == video_index[f]:
                continue
            common = ~np.isnan(rays[f, :, 0]) & ~np.isnan(rays[j, :, 0])
            if common.sum() < min(3, np.sum(~np.isnan(rays[f, :, 0]))) or not common.any():
                continue
            da, db, gap = closest_ray_points(centers[f], rays[f, common], centers[j], rays[j, common])
            if np.any(da < 0) or np.any(db < 0):
                continue
            if gap.mean() < best:
                best, partners[f] = gap.mean(), j
    return partners


def test_pairwise_initialization_matches_brute_force_with_missing_points():
    problem, _ = synthetic_problem(frames=60, points=6, miss=0.3)
    rays = viewing_rays(problem)
    centers = camera_normalization(problem.centers, problem.video_index).apply(problem.centers)
    init = initialize_depths(centers, rays, problem.video_index, memory_elements=500)  # several row blocks
    np.testing.assert_array_equal(init.partner, _brute_force_partners(centers, rays, problem.video_index))
    # Depths are those of the chosen pair, NaN where the frame does not observe the point.
    observed = ~np.isnan(rays[..., 0])
    partner_observed = observed[np.maximum(init.partner, 0)]
    assert np.all(np.isnan(init.depth[~observed]))
    assert np.all(np.isfinite(init.depth[observed & partner_observed & (init.partner >= 0)[:, None]]))


def test_initialization_is_close_on_noise_free_data():
    problem, truth = synthetic_problem(frames=120, points=6)
    from synthetic_motion import truth_array

    rays = viewing_rays(problem)
    norm = camera_normalization(problem.centers, problem.video_index)
    init = initialize_depths(norm.apply(problem.centers), rays, problem.video_index)
    points = norm.undo(norm.apply(problem.centers)[:, None] + init.depth[..., None] * rays)
    error = np.linalg.norm(points - truth_array(problem, truth), axis=-1)
    assert np.median(error) < 20.0  # mm; neighbours of other videos are 1/120 s away


def test_fill_missing_points_interpolates_within_a_video():
    points = np.full((5, 1, 3), np.nan)
    points[0, 0] = [0, 0, 0]
    points[4, 0] = [4, 8, 0]
    filled = fill_missing_points(points, np.zeros(5, dtype=int))
    np.testing.assert_allclose(filled[2, 0], [2, 4, 0])
