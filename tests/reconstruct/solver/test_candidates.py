import numpy as np
import pytest
from synthetic_motion import synthetic_problem, truth_array

from reconstruct.solver import candidates
from reconstruct.solver.alternation import SolverOptions, solve
from reconstruct.solver.candidates import (
    CandidateOptions,
    MovingWindows,
    VideoLayout,
    _fill_anchor_gaps,
    anchor_tolerance,
    coarse_to_fine_init,
    consistent_anchors,
    follow_w,
    pair_distances,
    window_pool,
)
from reconstruct.solver.initialize import (
    LAZY_ROUNDS,
    _distance_block,
    _Lines,
    _Side,
    bundle_distances,
    closest_ray_points,
    initialize_depths,
)
from reconstruct.solver.rays import camera_normalization, viewing_rays


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
            times[b][truth[:, b]] - all_times
        )
        truth[:, b] += nearest
    return video_index, layout, all_times, truth


def test_consistent_anchors_move_repeated_pose_matches_back_onto_the_clock_line():
    video_index, layout, times, truth = _two_clocks()
    anchor = truth.copy()
    anchor[40:100, 1] = np.maximum(anchor[40:100, 1] - 70, 0)  # a run matched to an earlier repetition
    anchor[350:380, 0] = np.minimum(anchor[350:380, 0] + 120, 299)
    anchor[[30, 200], 1] = [229, 0]  # isolated far matches
    anchor[5, 1] = 100  # before video 1 starts: no line position to move it to, it keeps its match
    with_times = consistent_anchors(anchor, video_index, layout, tolerance=3, times=times)
    assert with_times[5, 1] == 100
    with_times[5, 1] = truth[5, 1]
    assert np.abs(with_times - truth).max() <= 1
    without = consistent_anchors(anchor, video_index, layout, tolerance=12)
    without[5, 1] = truth[5, 1]
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


def test_moving_windows_rebuild_the_pool_only_when_an_anchor_moves(monkeypatch):
    import scipy.sparse as sp

    video_index = np.repeat([0, 1], [20, 20])
    anchor = np.zeros((40, 2), dtype=np.int64)
    anchor[:20, 0] = np.arange(20)
    anchor[:20, 1] = np.arange(20)
    anchor[20:, 0] = np.arange(20)
    anchor[20:, 1] = np.arange(20)
    windows = MovingWindows(anchor, video_index, CandidateOptions(half_window=2, recentre=3))
    built = []
    monkeypatch.setattr(candidates, "window_pool", lambda *a: built.append(1) or window_pool(*a))
    first = windows.pool()
    # W matches every frame with the same position of the other video: no anchor moves, the pool is reused
    same = sp.csc_matrix((np.ones(40), (np.r_[np.arange(20, 40), np.arange(20)], np.arange(40))), shape=(40, 40))
    windows.follow(same)
    assert windows.pool() is first and len(built) == 1
    # W now matches position p of video 0 with position p + 4 of video 1 (a clock offset past the slack): the
    # anchors move, and the pool is rebuilt
    rows = np.r_[20 + np.minimum(np.arange(20) + 4, 19), np.maximum(np.arange(20) - 4, 0)]
    shifted = sp.csc_matrix((np.ones(40), (rows, np.arange(40))), shape=(40, 40))
    windows.follow(shifted)
    pool = windows.pool()
    assert len(built) == 2 and windows.anchor[5, 1] == 9
    np.testing.assert_array_equal(pool, window_pool(windows.anchor, video_index, windows.layout, 2))


def _best_of_pairs(centers, rays, rows, cols, video_index, layout):
    """Per row frame and video the first position of least D over explicit pairs, by `pair_distances`."""
    F, V = len(video_index), len(layout.starts)
    D, _ = pair_distances(centers, rays, rows, cols)
    best_d = np.full((F, V), np.inf)
    position = np.full((F, V), -1, dtype=np.int64)
    for f, j, d in zip(rows, cols, D, strict=True):
        b = video_index[j]
        if d < best_d[f, b] or (d == best_d[f, b] and position[f, b] >= 0 and layout.position[j] < position[f, b]):
            best_d[f, b], position[f, b] = d, layout.position[j]
    return position, best_d


def _reference_init(centers, rays, video_index, options, times):
    """The windowed initialization spelled out pair by pair: the coarse frames against all coarse frames, then each
    frame against its `window_pool` (the explicit evaluation this module used before the matrix products)."""
    F = len(video_index)
    layout = VideoLayout.of(video_index)
    coarse = np.flatnonzero(layout.position % options.stride == 0)
    rows, cols = np.repeat(coarse, len(coarse)), np.tile(coarse, len(coarse))
    other = video_index[rows] != video_index[cols]
    position, _ = _best_of_pairs(centers, rays, rows[other], cols[other], video_index, layout)
    anchor = np.full(position.shape, -1, dtype=np.int64)
    anchor[coarse] = position[coarse]
    anchor = _fill_anchor_gaps(anchor, video_index, layout)
    anchor = consistent_anchors(anchor, video_index, layout, tolerance=options.stride, times=times)
    pool = window_pool(anchor, video_index, layout, options.stride + options.half_window)
    rows, cols = np.repeat(np.arange(F), pool.shape[1]), pool.ravel()
    position, best_d = _best_of_pairs(centers, rays, rows[cols >= 0], cols[cols >= 0], video_index, layout)
    anchor = np.where(position >= 0, position, anchor)
    anchor[np.arange(F), video_index] = layout.position
    anchor = consistent_anchors(anchor, video_index, layout, tolerance=anchor_tolerance(options, times), times=times)
    choice = np.argmin(best_d, axis=1)
    cost = best_d[np.arange(F), choice]
    partner = np.where(np.isfinite(cost), layout.starts[choice] + position[np.arange(F), choice], -1)
    depth = np.full(rays.shape[:2], np.nan)
    ok = partner >= 0
    _, depth[ok] = pair_distances(centers, rays, np.flatnonzero(ok), partner[ok])
    return partner, cost, depth, anchor


def _uneven_capture(seed=0):
    """A synthetic capture made awkward: 30 % missing, video 2 at half its frame rate, video 3 cut to 12 frames
    (shorter than a window), one frame sees nothing, one sees 2 points; and frame `target` of video 0 has
    LAZY_ROUNDS + 2 partners in video 1, at its anchor, whose rays meet its rays exactly, but behind its camera
    (D = 0, diverging), and frame `parallel` of video 0 one ray antiparallel to its time match's. Returns centers,
    rays, video_index, times, target, the mirrored frames, parallel."""
    problem, _ = synthetic_problem(frames=480, points=6, miss=0.3, seed=seed)
    centers, rays = _normalized(problem)
    layout = VideoLayout.of(problem.video_index)
    keep = (problem.video_index != 2) | (layout.position % 2 == 0)
    keep &= (problem.video_index != 3) | (layout.position < 12)
    centers, rays = centers[keep], rays[keep].copy()
    video_index, times = problem.video_index[keep], problem.times[keep]
    layout = VideoLayout.of(video_index)
    target = layout.starts[0] + 50
    seen = ~np.isnan(rays[target, :, 0])
    near = np.argmin(np.abs(times[video_index == 1] - times[target]))
    mirrored = layout.starts[1] + near + np.arange(-2, LAZY_ROUNDS)
    behind = centers[target] - rays[target]  # on the target's rays, one unit behind its camera
    direction = np.where(seen[:, None], behind, np.nan) - centers[mirrored][:, None, :]
    rays[mirrored] = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    rays[layout.starts[0] + 7] = np.nan
    rays[layout.starts[1] + 9, 2:] = np.nan
    # An antiparallel pair of rays (not counted) between a frame and its time match, which share 5 points.
    seen = ~np.isnan(rays[..., 0])
    match = layout.starts[1] + np.argmin(
        np.abs(times[video_index == 1][None] - times[video_index == 0][:, None]), axis=1
    )
    shared = np.sum(seen[video_index == 0] & seen[match], axis=1)
    parallel = np.flatnonzero(shared[80:] >= 5)[0] + 80
    point = np.flatnonzero(seen[parallel] & seen[match[parallel]])[0]
    rays[match[parallel], point] = -rays[parallel, point]
    return centers, rays, video_index, times, target, mirrored, parallel


@pytest.mark.parametrize(
    ("stride", "half_window", "pair_block", "blocks", "timed"),
    [
        (8, 4, 40_000, (2_000_000, 4096), True),  # defaults' shape: runs of frames, one coarse block per video pair
        (5, 3, 16, (7, 5), False),  # one frame per run, coarse bands of one row, explicit pairs 5 at a time; no times
    ],
)
def test_windowed_initialization_equals_the_explicit_pair_reference(
    monkeypatch, stride, half_window, pair_block, blocks, timed
):
    centers, rays, video_index, times, target, mirrored, parallel = _uneven_capture()
    options = CandidateOptions(stride=stride, half_window=half_window, pair_block=pair_block)
    times = times if timed else None
    partner, cost, depth, anchor = _reference_init(centers, rays, video_index, options, times)
    # The scene does what it says: the target's mirrored partners lie in its window, meet it, and diverge.
    _, _, gap = closest_ray_points(centers[target], rays[target], centers[mirrored][:, None], rays[mirrored])
    assert np.all(np.nanmean(gap, axis=1) < 1e-20)
    assert np.all(np.isinf(pair_distances(centers, rays, np.full(len(mirrored), target), mirrored)[0]))
    layout = VideoLayout.of(video_index)
    assert np.all(np.abs(layout.position[mirrored] - anchor[target, 1]) <= stride + half_window)
    assert partner[layout.starts[0] + 7] == -1 and partner[layout.starts[1] + 9] >= 0
    assert layout.lengths[3] < 2 * (stride + half_window) + 1
    match = np.flatnonzero(np.any(rays == -rays[parallel], axis=(1, 2)))
    assert partner[parallel] == match  # where the rule matters
    assert np.sum(np.isnan(depth[parallel]) & ~np.isnan(rays[match, :, 0]) & ~np.isnan(rays[parallel, :, 0])) == 1
    monkeypatch.setattr(candidates, "COARSE_BLOCK", blocks[0])
    monkeypatch.setattr(candidates, "EXPLICIT_PAIRS", blocks[1])
    init, windowed_anchor = coarse_to_fine_init(centers, rays, video_index, options, times=times)
    np.testing.assert_array_equal(windowed_anchor, anchor)
    np.testing.assert_array_equal(init.partner, partner)
    np.testing.assert_allclose(init.cost, cost, rtol=1e-9)  # inf where inf
    np.testing.assert_allclose(init.depth, depth, rtol=1e-9, atol=1e-12)  # NaN where NaN


def test_window_distances_of_both_videos_equal_the_dense_block():
    """One pass over runs of video 0's frames gives the windows of both videos (NaN where its runs miss one of
    video 1's), and the explicit pairs fill the rest; both equal the dense initialization's D, parallel pair too."""
    centers, rays, video_index, times, _, _, parallel = _uneven_capture()
    lines = _Lines.of(centers, rays)
    layout = VideoLayout.of(video_index)
    frames_a, frames_b = (np.flatnonzero(video_index == v) for v in (0, 1))
    dense, _ = _distance_block(lines, frames_a, frames_b, both=False)  # divergence not checked, as here
    dense_back, _ = _distance_block(lines, frames_b, frames_a, both=False)
    match = np.argmin(np.abs(times[frames_b][None] - times[frames_a][:, None]), axis=1)  # (L_a,) positions in b
    back = np.argmin(np.abs(times[frames_a][None] - times[frames_b][:, None]), axis=1)
    rng = np.random.default_rng(2)
    first_a = np.clip(match - 6 + rng.integers(-3, 4, len(match)), 0, len(frames_b) - 13)
    first_b = np.clip(back - 5 + rng.integers(-9, 10, len(back)), 0, len(frames_a) - 11)
    D, D_back = candidates._window_distances(
        lines, frames_a, first_a, _Side.cols(lines, frames_b), 13, 40_000, back=(first_b, 11)
    )
    np.testing.assert_allclose(
        D, np.take_along_axis(dense, first_a[:, None] + np.arange(13), axis=1), rtol=1e-12, atol=1e-20
    )  # the mirrored frames: D = 0 up to rounding
    expected_back = np.take_along_axis(dense_back, first_b[:, None] + np.arange(11), axis=1)
    covered = ~np.isnan(D_back)
    assert 0.5 < covered.mean() < 1.0  # the shifted windows stick out of the runs' ranges
    np.testing.assert_allclose(D_back[covered], expected_back[covered], rtol=1e-12, atol=1e-20)
    r, k = np.nonzero(~covered)
    r = np.concatenate([r, [match[parallel - layout.starts[0]]]])
    cols = np.concatenate([first_b[r[:-1]] + k, [parallel - layout.starts[0]]])
    explicit = candidates._explicit_distances(lines, frames_b[r], frames_a[cols])
    np.testing.assert_allclose(explicit, dense_back[r, cols], rtol=1e-12, atol=1e-20)
    assert np.isfinite(explicit[-1])
