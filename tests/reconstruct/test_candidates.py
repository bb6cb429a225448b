import numpy as np
from synthetic_motion import synthetic_problem, truth_array

from reconstruct.candidates import CandidateOptions, VideoLayout, coarse_to_fine_init, pair_distances, window_pool
from reconstruct.initialize import bundle_distances, initialize_depths
from reconstruct.rays import camera_normalization, viewing_rays
from reconstruct.solver import SolverOptions, solve


def _normalized(problem):
    normalization = camera_normalization(problem.centers, problem.video_index)
    return normalization.apply(problem.centers), viewing_rays(problem)


def test_pair_distances_equal_the_dense_bundle_distances():
    problem, _ = synthetic_problem(frames=60, points=5, miss=0.2)
    centers, rays = _normalized(problem)
    rows = np.arange(0, 60, 7)
    D, depth = bundle_distances(centers, rays, rows, problem.video_index)
    f = np.repeat(rows, 60)
    j = np.tile(np.arange(60), len(rows))
    other = problem.video_index[f] != problem.video_index[j]
    D_pairs, depth_pairs = pair_distances(centers, rays, f[other], j[other])
    np.testing.assert_allclose(D_pairs, D.ravel()[other], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(depth_pairs, depth.reshape(-1, 5)[other], rtol=1e-9, atol=1e-12)


def test_window_pool_holds_only_other_videos_within_the_window():
    video_index = np.repeat([0, 1, 2], [10, 12, 8])
    layout = VideoLayout.of(video_index)
    anchor = np.zeros((30, 3), dtype=np.int64)
    anchor[:, 1] = 11  # at the end of video 1: the window is clipped and shifted inside
    pool = window_pool(anchor, video_index, layout, half_window=2)
    for f in range(30):
        members = pool[f][pool[f] >= 0]
        assert len(np.unique(members)) == len(members)
        assert not np.any(video_index[members] == video_index[f])
        assert set(layout.position[members[video_index[members] == 1]]) <= set(range(7, 12))


def test_coarse_to_fine_initialization_finds_the_dense_partners():
    problem, _ = synthetic_problem(frames=400, points=6)
    centers, rays = _normalized(problem)
    dense = initialize_depths(centers, rays, problem.video_index)
    windowed, anchor = coarse_to_fine_init(centers, rays, problem.video_index, CandidateOptions(stride=8))
    assert np.mean(windowed.partner == dense.partner) > 0.95
    assert anchor.shape == (400, len(problem.video_names))


def test_windowed_solve_matches_the_dense_solve():
    problem, truth = synthetic_problem(frames=400, points=6)
    expected = truth_array(problem, truth)
    shares = []
    for dense_limit in (10**6, 0):
        result = solve(problem, SolverOptions(dense_limit=dense_limit, candidates=CandidateOptions(stride=8)))
        shares.append(np.mean(np.linalg.norm(result.points - expected, axis=-1) < 10.0))
    assert shares[1] > 0.99
    assert shares[1] >= shares[0] - 0.003
