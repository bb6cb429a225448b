import numpy as np
from synthetic_motion import synthetic_problem, truth_array

from reconstruct.candidates import (
    CandidateOptions,
    VideoLayout,
    coarse_to_fine_init,
    consistent_anchors,
    follow_w,
    pair_distances,
    window_pool,
)
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


def _two_clocks(seed=0):
    """Two videos at 30 and 24 fps, video 1 starting 0.5 s later, with 1 ms jitter: each frame's true anchor."""
    rng = np.random.default_rng(seed)
    times = [np.arange(300) / 30 + rng.normal(0, 1e-3, 300), 0.5 + np.arange(230) / 24 + rng.normal(0, 1e-3, 230)]
    video_index = np.repeat([0, 1], [300, 230])
    layout = VideoLayout.of(video_index)
    all_times = np.concatenate(times)
    truth = np.zeros((530, 2), dtype=np.int64)
    for b in range(2):
        truth[:, b] = np.clip(np.searchsorted(times[b], all_times - 0.5 / 30), 0, len(times[b]) - 1)
        nearest = np.abs(times[b][np.minimum(truth[:, b] + 1, len(times[b]) - 1)] - all_times) < np.abs(
            times[b][truth[:, b]] - all_times)
        truth[:, b] += nearest
    return video_index, layout, all_times, truth


def test_consistent_anchors_move_repeated_pose_matches_back_onto_the_clock_line():
    video_index, layout, times, truth = _two_clocks()
    anchor = truth.copy()
    anchor[40:100, 1] = np.maximum(anchor[40:100, 1] - 70, 0)  # a run matched to an earlier repetition
    anchor[350:380, 0] = np.minimum(anchor[350:380, 0] + 120, 299)
    anchor[[10, 200], 1] = [229, 0]  # isolated far matches
    with_times = consistent_anchors(anchor, video_index, layout, tolerance=3, times=times)
    assert np.abs(with_times - truth).max() <= 1
    without = consistent_anchors(anchor, video_index, layout, tolerance=12)
    assert np.abs(without - truth).max() <= 12
    np.testing.assert_array_equal(consistent_anchors(truth, video_index, layout, tolerance=3, times=times), truth)


def test_follow_w_moves_an_anchor_only_past_the_slack_and_to_the_largest_entry():
    import scipy.sparse as sp

    video_index = np.repeat([0, 1], [20, 20])
    layout = VideoLayout.of(video_index)
    anchor = np.zeros((40, 2), dtype=np.int64)
    anchor[:20, 1] = 5
    # frame 0: weights at positions 6 (0.3) and 15 (0.7) of video 1; frame 1: 0.9 at position 7
    W = sp.csc_matrix(([0.3, 0.7, 0.9], ([26, 35, 27], [0, 0, 1])), shape=(40, 40))
    moved = follow_w(anchor, W, video_index, layout, slack=3)
    assert moved[0, 1] == 15  # the largest entry, not the weighted mean (12)
    assert moved[1, 1] == 5  # within the slack: the pool stays put
