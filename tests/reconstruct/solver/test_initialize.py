import numpy as np
from synthetic_motion import synthetic_problem

from reconstruct.solver.initialize import (
    LAZY_ROUNDS,
    bundle_distances,
    closest_ray_points,
    fill_missing_points,
    initialize_depths,
)
from reconstruct.solver.rays import camera_normalization, viewing_rays


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


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _awkward_scene(seed=3):
    """3 videos x 10 frames, 6 points, a different shape per frame, 30 % missing; frame 0 has LAZY_ROUNDS + 2
    partners in video 1 whose rays meet its rays exactly but behind its camera (D = 0, diverging), frames 1 and 20
    are each other's best partners with one pair of antiparallel rays (not counted), frame 29 sees nothing, frame
    28 sees 2 points."""
    rng = np.random.default_rng(seed)
    V, per, P = 3, 10, 6
    video_index = np.repeat(np.arange(V), per)
    F = V * per
    points = rng.normal(scale=0.3, size=(F, P, 3))
    centers = 3.0 * _unit(rng.normal(size=(F, 3)))
    rays = _unit(points - centers[:, None])
    mirrored = range(per, per + LAZY_ROUNDS + 2)
    behind = 2.0 * centers[0] - points[0]  # frame 0's points reflected through its camera centre
    for j in mirrored:
        rays[j] = _unit(behind - centers[j])
    # Frame 20 sees frame 1's shape (its best partner) from beyond point 0, looking back along frame 1's ray.
    points[20] = points[1] + rng.normal(scale=1e-3, size=(P, 3))
    points[20, 0] = points[1, 0]
    centers[20] = 2.0 * points[1, 0] - centers[1]
    rays[20] = _unit(points[20] - centers[20])
    missing = rng.random((F, P)) < 0.3
    missing[[0, 1, 20, *mirrored]] = False
    missing[28] = [False, False, True, True, True, True]
    missing[29] = True
    rays[missing] = np.nan
    return centers, rays, video_index, list(mirrored)


def _reference(centers, rays, video_index):
    """D (F, F) and each pair's depths (F, F, P) by `closest_ray_points`, pair by pair, with the rules of the
    initialization spelled out."""
    F, P = rays.shape[:2]
    D = np.full((F, F), np.inf)
    naive = np.full((F, F), np.inf)  # without the divergence rule
    depth = np.full((F, F, P), np.nan)
    observed = ~np.isnan(rays[..., 0])
    for f in range(F):
        for j in range(F):
            if video_index[f] == video_index[j]:
                continue
            da, db, gap = closest_ray_points(centers[f], rays[f], centers[j], rays[j])
            usable = np.isfinite(gap)  # both observe the point, rays not parallel
            depth[f, j] = np.where(usable, da, np.nan)
            if usable.sum() < min(3, max(observed[f].sum(), 1)):
                continue
            naive[f, j] = gap[usable].mean()
            if not (np.any(da[usable] < 0) or np.any(db[usable] < 0)):
                D[f, j] = naive[f, j]
    return D, naive, depth


def test_initialization_equals_the_pairwise_reference_with_diverging_and_parallel_pairs():
    centers, rays, video_index, mirrored = _awkward_scene()
    D, naive, depth = _reference(centers, rays, video_index)
    # The scene does what it says: frame 0's best bundles diverge, one pair has a parallel ray.
    assert np.all(naive[0, mirrored] < 1e-20) and np.all(np.isinf(D[0, mirrored]))
    has = np.isfinite(D).any(axis=1)
    partner = np.where(has, np.argmin(D, axis=1), -1)
    assert partner[29] == -1 and partner[28] >= 0 and partner[0] not in mirrored
    assert partner[1] == 20 and partner[20] == 1 and np.isnan(depth[1, 20, 0]) and np.isnan(depth[20, 1, 0])
    F = len(centers)
    expected = np.where(has[:, None], depth[np.arange(F), partner], np.nan)
    for memory_elements in (1, 30, 2_000_000):  # bands of one row, tiles, whole blocks
        init = initialize_depths(centers, rays, video_index, memory_elements=memory_elements)
        np.testing.assert_array_equal(init.partner, partner)
        np.testing.assert_allclose(init.cost[has], D[np.arange(F), partner][has], rtol=1e-9)
        assert np.all(np.isinf(init.cost[~has]))
        np.testing.assert_allclose(init.depth, expected, rtol=1e-9, atol=1e-12)  # NaN where NaN
    # Frames of a video need not be contiguous.
    order = np.random.default_rng(1).permutation(F)
    init = initialize_depths(centers[order], rays[order], video_index[order])
    back = np.argsort(order)
    np.testing.assert_array_equal(np.where(init.partner >= 0, order[init.partner], -1)[back], partner)
    np.testing.assert_allclose(init.depth[back], expected, rtol=1e-9, atol=1e-12)


def test_bundle_distances_equal_the_pairwise_reference():
    centers, rays, video_index, _ = _awkward_scene()
    D, _, depth = _reference(centers, rays, video_index)
    rows = np.array([0, 1, 5, 12, 20, 28, 29])
    D_rows, depth_rows = bundle_distances(centers, rays, rows, video_index)
    np.testing.assert_array_equal(np.isinf(D_rows), np.isinf(D[rows]))
    np.testing.assert_allclose(D_rows, D[rows], rtol=1e-9)
    np.testing.assert_allclose(depth_rows, depth[rows], rtol=1e-9, atol=1e-12)


def test_fill_missing_points_interpolates_within_a_video():
    points = np.full((5, 1, 3), np.nan)
    points[0, 0] = [0, 0, 0]
    points[4, 0] = [4, 8, 0]
    filled = fill_missing_points(points, np.zeros(5, dtype=int))
    np.testing.assert_allclose(filled[2, 0], [2, 4, 0])


def test_a_point_without_any_start_starts_at_the_others_mean():
    """A point whose rays never met another video's in front of both cameras (cameras given to the wrong videos, a
    helper's real hand recording): the other points' mean on each frame, not NaN (the W-step's Gram matrices of NaN
    shapes raised LinAlgError)."""
    points = np.full((4, 3, 3), np.nan)
    points[:, 0] = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]
    points[:, 1] = [[0, 2, 0], [1, 2, 0], [2, 2, 0], [3, 2, 0]]
    filled = fill_missing_points(points, np.array([0, 0, 1, 1]))
    assert np.isfinite(filled).all()
    np.testing.assert_allclose(filled[:, 2], [[0, 1, 0], [1, 1, 0], [2, 1, 0], [3, 1, 0]])
