import json
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from synthetic_motion import smooth_motion, synthetic_problem, truth_array

from reconstruct.inputs import build_problem
from reconstruct.solver.alternation import solve
from reconstruct.solver.rays import viewing_rays
from reconstruct.trust import (
    TrustOptions,
    TrustPreset,
    components,
    flag_points,
    neighbourhood_condition,
    neighbourhoods,
    off_videos,
    preset_options,
    sequence_jump,
    trust_measures,
    video_smoothness,
)


@pytest.fixture(scope="module")
def solved():
    """A small noise-free solve of smooth motion (4 cameras, 30 Hz each) and its truth in problem order."""
    problem, truth = synthetic_problem(frames=120, points=5, seed=3)
    result = solve(problem)
    return problem, result, truth_array(problem, truth)


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _paper_a(W, rays):
    """The paper's Eq. (A) for one point, every frame observed: A_gh = [(I - W)(I - W)^T]_gh r_g.r_h."""
    M = np.eye(len(rays)) - W
    return (M @ M.T) * (rays @ rays.T)


def test_two_frames_expressing_each_other_have_the_closed_form_sigma_min():
    # W_jf = W_fj = 1: A = [[2, -2c], [-2c, 2]] with c = r_f.r_j, so sigma_min = 2 (1 - c).
    W = np.array([[0.0, 1.0], [1.0, 0.0]])
    for degrees in (20.0, 60.0, 90.0):
        a = np.radians(degrees)
        rays = np.array([[1.0, 0.0, 0.0], [np.cos(a), np.sin(a), 0.0]])
        A = _paper_a(W, rays)
        np.testing.assert_allclose(A, [[2, -2 * np.cos(a)], [-2 * np.cos(a), 2]], atol=1e-12)
        M = np.eye(2) - W
        condition = neighbourhood_condition((M @ M.T)[None], rays[None])[0]
        assert condition == pytest.approx(1 / (2 * (1 - np.cos(a))), rel=1e-9)


def test_condition_matches_a_dense_construction_with_missing_observations():
    rng = np.random.default_rng(1)
    n = 4
    W = rng.random((n, n))
    np.fill_diagonal(W, 0)
    W /= W.sum(axis=0, keepdims=True)
    M = np.eye(n) - W
    gram = M @ M.T + 0.3 * np.eye(n)  # a neighbourhood held by frames outside it: positive definite
    rays = rng.normal(size=(n, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays[2] = np.nan  # unobserved: 3 free coordinates
    # Dense: unknowns l_g along r_g (observed) or e_g in R^3 (unobserved); A = B^T (gram kron I3) B.
    columns = []
    for g in range(n):
        basis = np.eye(3) if np.isnan(rays[g]).any() else rays[g][:, None]
        block = np.zeros((3 * n, basis.shape[1]))
        block[3 * g : 3 * g + 3] = basis
        columns.append(block)
    B = np.hstack(columns)
    A = B.T @ np.kron(gram, np.eye(3)) @ B
    expected = 1 / np.linalg.eigvalsh(A)[0]
    assert neighbourhood_condition(gram[None], rays[None])[0] == pytest.approx(expected, rel=1e-8)
    # Unused slots do not change it.
    padded_gram = np.zeros((1, n + 2, n + 2))
    padded_gram[0, :n, :n] = gram
    padded_rays = np.concatenate([rays, np.full((2, 3), 7.0)])[None]
    valid = np.array([[True] * n + [False, False]])
    assert neighbourhood_condition(padded_gram, padded_rays, valid)[0] == pytest.approx(expected, rel=1e-8)


def test_parallel_rays_are_degenerate_and_converging_rays_are_not():
    # Three frames expressing each other (columns of W on the simplex, the group closed): with parallel rays a
    # common shift along them costs nothing, so A is singular.
    W = np.array([[0.0, 0.5, 0.5], [0.5, 0.0, 0.5], [0.5, 0.5, 0.0]])
    M = np.eye(3) - W
    gram = (M @ M.T)[None]
    parallel = np.tile(_unit([0.2, 0.1, 1.0]), (3, 1))[None]
    assert neighbourhood_condition(gram, parallel)[0] > 1e10
    # Nearly parallel (one handheld camera) is badly conditioned, cameras 90 degrees apart are fine.
    nearly = np.array([_unit([0.0, 0.0, 1.0]), _unit([0.01, 0.0, 1.0]), _unit([0.0, 0.01, 1.0])])[None]
    spread = np.array([_unit([1.0, 0.0, 0.0]), _unit([0.0, 1.0, 0.0]), _unit([0.0, 0.0, 1.0])])[None]
    assert neighbourhood_condition(gram, nearly)[0] > 1e3
    assert neighbourhood_condition(gram, spread)[0] < 10


def test_neighbourhoods_take_both_directions_strongest_first():
    W = sp.csc_matrix(
        np.array([[0.0, 0.7, 0.0, 0.01], [0.6, 0.0, 0.0, 0.0], [0.4, 0.3, 0.0, 0.99], [0.0, 0.0, 1.0, 0.0]])
    )
    hood = neighbourhoods(W, min_weight=0.02, max_neighbours=2)
    np.testing.assert_array_equal(hood[0], [0, 1, 2])  # W_10 = 0.6 / W_01 = 0.7 -> 0.7, W_20 = 0.4
    np.testing.assert_array_equal(hood[3], [3, 2, -1])  # W_03 = 0.01 is dust


def test_points_on_their_rays_have_zero_ray_distance_and_an_offset_is_measured(solved):
    problem, result, truth = solved
    trust = trust_measures(problem, result)
    observed = problem.observed
    # The soft constraint (lambda3 = 100) keeps noise-free points essentially on their rays.
    assert np.nanmax(trust.ray_distance) < 1.0  # mm
    # Put every observed point exactly on its ray (at the truth's depth), then push one off by 25 mm.
    rays = viewing_rays(problem)
    centers = problem.centers[:, None, :]
    depth = np.sum((truth - centers) * rays, axis=-1)
    on_ray = np.where(observed[..., None], centers + depth[..., None] * rays, result.points)
    f, p = 10, 2
    side = np.cross(rays[f, p], [0.0, 0.0, 1.0])
    on_ray[f, p] += 25.0 * _unit(side)
    trust = trust_measures(problem, replace(result, points=on_ray))
    distance = trust.ray_distance.copy()
    assert distance[f, p] == pytest.approx(25.0, rel=1e-9)
    distance[f, p] = 0.0
    assert np.nanmax(distance) < 1e-9
    # Seen from the camera: an angle of atan(25 / depth) times the focal length.
    expected_px = problem.K[f, 0, 0] * np.arctan2(25.0, depth[f, p])
    assert trust.reprojection_px[f, p] == pytest.approx(expected_px, rel=1e-6)


def test_unobserved_points_have_no_ray_distance_and_unreconstructed_ones_are_empty(solved):
    problem, result, _ = solved
    problem = replace(problem, uv=problem.uv.copy())
    problem.uv[5, 1] = np.nan
    points = result.points.copy()
    points[:, 4] = np.nan  # as the solver leaves a point seen in one video
    trust = trust_measures(problem, replace(result, points=points))
    assert np.isnan(trust.ray_distance[5, 1]) and np.isfinite(trust.residual[5, 1])
    assert np.isfinite(trust.condition[5, 1])
    columns = trust.columns()
    for name, values in columns.items():
        assert values.shape == (problem.num_frames, problem.num_points), name
        assert np.all(np.isnan(values[:, 4])), name
    assert not trust.flag[:, 4].any()


def test_residual_is_the_distance_to_the_w_combination(solved):
    problem, result, _ = solved
    trust = trust_measures(problem, result)
    W = result.W.to_csc().toarray()
    f, p = 30, 3
    combination = np.einsum("j,jk->k", W[:, f], result.points[:, p])
    assert trust.residual[f, p] == pytest.approx(np.linalg.norm(result.points[f, p] - combination), rel=1e-9)
    # The frame's RMS residual reported by the solver is the RMS of the points' residuals.
    np.testing.assert_allclose(np.sqrt(np.mean(trust.residual**2, axis=1)), result.residual, rtol=1e-6)


@pytest.mark.parametrize("preset", list(TrustPreset))
def test_flags_catch_injected_large_errors_and_leave_a_good_solve_mostly_unflagged(solved, preset):
    problem, result, truth = solved
    options = preset_options(preset)
    trust = trust_measures(problem, result, options)
    error = np.linalg.norm(result.points - truth, axis=-1)
    assert np.median(error) < 2.0  # the solve itself is good
    assert trust.flag.mean() < 0.05
    # Move 12 points (away from the clip's ends) 150 mm along their rays: a wrong depth the rays cannot see.
    rng = np.random.default_rng(7)
    F, P = problem.num_frames, problem.num_points
    rays = viewing_rays(problem)
    chosen = rng.choice(np.arange(F * P).reshape(F, P)[10:-10].ravel(), size=12, replace=False)
    frames, points_ = np.unravel_index(chosen, (F, P))
    moved = result.points.copy()
    moved[frames, points_] += 150.0 * rays[frames, points_]
    flagged = trust_measures(problem, replace(result, points=moved), options).flag
    assert flagged[frames, points_].mean() >= 0.9


def test_summary_and_columns_are_json_ready(solved):
    problem, result, _ = solved
    trust = trust_measures(problem, result, TrustOptions(residual_px=0.0, relative=0.0))  # flag everything
    summary = trust.summary()
    text = json.dumps(summary, allow_nan=False)
    assert "rule" in summary and summary["flagged"] == problem.num_frames * problem.num_points
    assert summary["flagged_share"] == pytest.approx(1.0)
    assert set(summary["measures"]) >= {"condition", "residual", "ray_distance"}
    assert json.loads(text)["measures"]["residual"]["median"] > 0
    columns = trust.columns()
    assert set(columns) == {
        "condition",
        "residual",
        "residual_px",
        "bound_px",
        "ray_distance",
        "reprojection_px",
        "support",
        "sequence_jump",
        "component",
        "smoothness_px",
        "step_px",
        "views",
        "flag",
    }
    assert set(np.unique(columns["flag"])) == {1.0}


def test_support_is_the_weight_on_neighbours_that_observe_the_point(solved):
    problem, result, _ = solved
    W = result.W.to_csc().toarray()
    f, p = 40, 0
    neighbours = np.flatnonzero(W[:, f] > 0)
    problem = replace(problem, uv=problem.uv.copy())
    problem.uv[f, p] = np.nan
    problem.uv[neighbours[0], p] = np.nan
    trust = trust_measures(problem, result)
    assert trust.support[f, p] == pytest.approx(1.0 - W[neighbours[0], f] / W[:, f].sum(), abs=1e-9)
    problem.uv[neighbours, p] = np.nan
    assert trust_measures(problem, result).support[f, p] == pytest.approx(0.0, abs=1e-12)


def test_measures_in_pixels_and_the_flag_do_not_depend_on_the_unit_of_length(solved):
    problem, result, _ = solved
    moved = result.points.copy()
    moved[20:23, 1] += 200.0  # a few wrong points so that something is flagged
    in_mm = trust_measures(problem, replace(result, points=moved))
    in_m = trust_measures(replace(problem, t=problem.t / 1000.0), replace(result, points=moved / 1000.0))
    np.testing.assert_allclose(in_m.condition, in_mm.condition, rtol=1e-9)
    np.testing.assert_allclose(in_m.residual_px, in_mm.residual_px, rtol=1e-6)
    np.testing.assert_allclose(in_m.residual * 1000.0, in_mm.residual, rtol=1e-6)
    np.testing.assert_array_equal(in_m.flag, in_mm.flag)
    assert in_mm.flag[20:23, 1].all()


def _interleaved_w(times, video_index):
    """W that interpolates every frame from the nearest earlier and later frames of other videos."""
    F = len(times)
    W = np.zeros((F, F))
    for f in range(F):
        other = np.flatnonzero(video_index != video_index[f])
        before = other[times[other] < times[f]]
        after = other[times[other] > times[f]]
        if len(before) and len(after):
            a, b = before[np.argmax(times[before])], after[np.argmin(times[after])]
            w = (times[b] - times[f]) / (times[b] - times[a])
            W[a, f], W[b, f] = w, 1 - w
        else:  # the clip's ends: the nearest frame of another video
            W[other[np.argmin(np.abs(times[other] - times[f]))], f] = 1.0
    return W


def test_sequence_jump_is_small_for_interleaved_frames_and_large_where_two_far_frames_swap_partners():
    # Two cameras taking turns at 30 Hz each: capture k at k / 60 s.
    count = 60
    times_all = np.arange(count) / 60.0
    video_all = np.arange(count) % 2
    order = np.argsort(video_all, kind="stable")  # frames grouped by video, as in a Problem
    times, video_index = times_all[order], video_all[order]
    W = _interleaved_w(times, video_index)
    jump = sequence_jump(sp.csc_matrix(W), video_index, times)
    assert np.nanmax(jump) <= 2.0
    # Frames at 0.2 s and 0.8 s (both of video 0) represent each other through video 1's frames 0.6 s away.
    f = int(np.flatnonzero((video_index == 0) & np.isclose(times, 0.2))[0])
    far = int(np.flatnonzero((video_index == 1) & np.isclose(times, 0.2 + 0.6 + 1 / 60))[0])
    W[:, f] = 0.0
    W[far, f] = 1.0
    jump = sequence_jump(sp.csc_matrix(W), video_index, times)
    # Its neighbours moved by 0.6 s while the video advanced 1/30 s: ~18 frame gaps on both sides of f.
    assert jump[f] > 15
    assert np.nanmax(np.delete(jump, [f - 1, f, f + 1])) <= 2.0
    # Unknown times: no measure.
    assert np.all(np.isnan(sequence_jump(sp.csc_matrix(W), video_index, np.full(count, np.nan))))


def test_components_find_islands_of_frames_that_only_represent_each_other():
    chain = np.zeros((6, 6))
    for f in range(6):  # 0-1-2-3 chained, 4 and 5 only represent each other
        if f < 4:
            for j in (f - 1, f + 1):
                if 0 <= j < 4:
                    chain[j, f] = 0.5 if f in (1, 2) else 1.0
    chain[5, 4] = chain[4, 5] = 1.0
    np.testing.assert_array_equal(components(sp.csc_matrix(chain), 0.02), [4, 4, 4, 4, 2, 2])
    chain[4, 3] = 0.01  # dust does not link
    np.testing.assert_array_equal(components(sp.csc_matrix(chain), 0.02), [4, 4, 4, 4, 2, 2])


def test_an_island_is_flagged_only_when_asked(solved):
    problem, result, _ = solved
    trust = trust_measures(problem, result)
    assert np.all(trust.component[trust.reconstructed] == problem.num_frames)  # one chain through the clip
    everything = trust_measures(problem, result, TrustOptions(min_component=problem.num_frames + 1)).flag
    assert everything[trust.reconstructed].all()


def test_video_smoothness_is_zero_on_linear_motion_and_measures_a_jump():
    # One video, frames 0..5 at uneven times, a point moving at constant velocity; then frame 3 jumps 40 units.
    times = np.array([0.0, 0.1, 0.15, 0.3, 0.4, 0.55])
    points = (np.array([1.0, -2.0, 0.5])[None, :] * times[:, None] + np.array([5.0, 0.0, 1.0]))[:, None, :]
    video_index = np.zeros(6, dtype=np.int64)
    frames = np.arange(6)
    smooth = video_smoothness(points, video_index, frames, times)
    assert np.isnan(smooth[0, 0]) and np.isnan(smooth[5, 0])
    np.testing.assert_allclose(smooth[1:5, 0], 0.0, atol=1e-12)
    points[3, 0, 2] += 40.0
    smooth = video_smoothness(points, video_index, frames, times)
    assert smooth[3, 0] == pytest.approx(40.0)
    # Its neighbours see part of the jump through their interpolation: frame 2 (0.15 s) is 1/4 of 0.1 -> 0.3 s.
    assert smooth[2, 0] == pytest.approx(40.0 / 4.0)


@pytest.fixture(scope="module")
def noisy_solves():
    """The fixture's capture with Gaussian pixel noise of 1 and 2 px (tracked 2D is noisy), solved."""
    out = {}
    for noise in (1.0, 2.0):
        problem, truth = synthetic_problem(frames=120, points=5, seed=3, noise_px=noise)
        out[noise] = (problem, solve(problem), truth_array(problem, truth))
    return out


def test_the_default_rule_follows_the_noise_level_and_catches_gross_errors(noisy_solves):
    options = preset_options(TrustPreset.SENSITIVE)  # the default of `dynrecon solve`
    limits = {}
    for noise, (problem, result, truth) in noisy_solves.items():
        trust = trust_measures(problem, result, options)
        error = np.linalg.norm(result.points - truth, axis=-1)
        assert error.max() < 30.0  # nothing large to find: the flag should stay quiet
        assert trust.flag.mean() < 0.08  # measured: 5.5 % (1 px), 5.0 % (2 px)
        limits[noise] = trust.limits["residual_px"]
        # A few gross errors: 150 mm along the rays (a depth the rays cannot see), away from the clip's ends.
        rng = np.random.default_rng(7)
        F, P = problem.num_frames, problem.num_points
        rays = viewing_rays(problem)
        chosen = rng.choice(np.arange(F * P).reshape(F, P)[10:-10].ravel(), size=12, replace=False)
        frames, points_ = np.unravel_index(chosen, (F, P))
        moved = result.points.copy()
        moved[frames, points_] += 150.0 * rays[frames, points_]
        flagged = trust_measures(problem, replace(result, points=moved), options).flag
        assert flagged[frames, points_].all()
        assert np.delete(flagged.ravel(), chosen).mean() < 0.18  # measured: 13.1 % (1 px), 10.9 % (2 px)
    # The residual limit is a multiple of the capture's own median residual, not a fixed pixel count: twice the
    # noise, about twice the limit (measured 2.1 and 3.9 px).
    assert limits[2.0] > 1.6 * limits[1.0] > 1.6 * 1.5


def test_flag_points_is_scale_free_above_its_floors():
    rng = np.random.default_rng(0)
    shape = (200, 6)
    reconstructed = np.ones(shape, dtype=bool)
    base = {
        "residual_px": np.abs(rng.normal(size=shape)) + 0.5,
        "bound_px": 20.0 * rng.lognormal(size=shape),
        "sequence_jump": np.abs(rng.normal(scale=5.0, size=shape)) + 5.0,
        "component": np.full(shape, 200.0),
        "smoothness_px": np.abs(rng.normal(size=shape)),
        "support": np.ones(shape),
        "observed": np.ones(shape, dtype=bool),
        "step_px": np.abs(rng.normal(size=shape)) + 1.0,
        "video_end": np.zeros(shape, dtype=bool),
    }
    options = preset_options(TrustPreset.SENSITIVE)
    flag, limits = flag_points(options, reconstructed, base)
    assert 0.0 < flag.mean() < 0.2
    # A noisier capture (every measure in pixels x 4; jumps x 4, as a periodic motion's): the same points flagged.
    scaled = {
        k: v * 4.0 if k in ("residual_px", "bound_px", "sequence_jump", "step_px") else v for k, v in base.items()
    }
    flag4, limits4 = flag_points(options, reconstructed, scaled)
    np.testing.assert_array_equal(flag4, flag)
    assert limits4["residual_px"] == pytest.approx(4.0 * limits["residual_px"])
    # Support below the limit flags an unobserved point (built from neighbours that miss it too), not an observed
    # one (its ray holds it); a fast point at a video's first or last frame is flagged, and only there.
    base["support"][[3, 5], 2] = 0.05
    base["observed"][3, 2] = False
    base["step_px"][[0, 100], 4] = 50.0
    base["video_end"][0] = True
    flag, _ = flag_points(options, reconstructed, base)
    assert flag[3, 2] and not flag[5, 2] and flag[0, 4] and not flag[100, 4]
    assert not flag_points(preset_options(TrustPreset.BALANCED), reconstructed, base)[0][[3, 0], [2, 4]].any()


@pytest.mark.parametrize("preset", list(TrustPreset))
def test_a_video_whose_points_name_other_things_is_flagged_whole_and_reported(solved, preset, caplog):
    from simulation.simulate import SimulationOptions, simulate_capture

    assert trust_measures(*solved[:2], preset_options(preset)).off_videos == {}
    # cam0's tracks name each point after the next one: another subject as far as the other videos can tell.
    capture = simulate_capture(smooth_motion(120, 5, 3), 120.0, SimulationOptions(seed=3))
    tracks = capture.tracks
    names = tracks.point_names()
    following = dict(zip(names, names[1:] + names[:1], strict=True))
    tracks.point = [following[p] if v == "cam0" else p for v, p in zip(tracks.video, tracks.point, strict=True)]
    problem = build_problem(capture.cameras, tracks, point_names=capture.truth.point_names)
    trust = trust_measures(problem, solve(problem), preset_options(preset))
    assert list(trust.off_videos) == ["cam0"]
    assert trust.off_videos["cam0"]["median_residual_px"] > trust.off_videos["cam0"]["limit_px"]
    own = problem.video_index == 0
    assert trust.flag[own][trust.reconstructed[own]].all()
    assert trust.flag[~own].mean() < 0.5
    assert json.loads(json.dumps(trust.summary()))["off_videos"] == trust.off_videos
    assert "cam0: its points miss what the other videos see" in caplog.text
    assert "another subject (import-tracks --person)" in caplog.text  # several points: a person's


def test_off_videos_needs_three_videos_and_follows_the_others_median():
    options = TrustOptions()  # residual_px floor 5, video_relative 3
    video_index = np.repeat([0, 1, 2], 10)
    reconstructed = np.ones((30, 2), dtype=bool)
    residual_px = np.repeat([[6.0], [7.0], [40.0]], 10, axis=0) * np.ones((1, 2))
    assert off_videos(options, reconstructed, residual_px, video_index) == {2: (40.0, pytest.approx(19.5))}
    # two videos: neither can be told to be the odd one
    assert off_videos(options, reconstructed[:20], residual_px[:20], video_index[:20]) == {}
    # under the floor: clean solves do not flag their round-off
    assert off_videos(options, reconstructed, residual_px / 10, video_index) == {}
    assert off_videos(replace(options, video_relative=0.0), reconstructed, residual_px, video_index) == {}


def test_flag_points_takes_its_medians_over_observed_points():
    # Unobserved points follow their neighbours (residual ~0): where they are most of a solve, a median over every
    # point would set the limit under the observations' own noise and flag most observed points.
    rng = np.random.default_rng(2)
    shape = (300, 4)
    observed = np.zeros(shape, dtype=bool)
    observed[:100] = True
    measures = {
        "residual_px": np.where(observed, 3.0 + np.abs(rng.normal(size=shape)), 0.05),
        "bound_px": np.ones(shape),
        "sequence_jump": np.zeros(shape),
        "component": np.full(shape, 300.0),
        "smoothness_px": np.zeros(shape),
        "support": np.ones(shape),
        "observed": observed,
        "step_px": np.ones(shape),
        "video_end": np.zeros(shape, dtype=bool),
    }
    reconstructed = np.ones(shape, dtype=bool)
    options = preset_options(TrustPreset.SENSITIVE)
    flag, limits = flag_points(options, reconstructed, measures)
    assert limits["residual_px"] == pytest.approx(2.5 * np.median(measures["residual_px"][observed]))
    assert flag[observed].mean() < 0.05
    # nothing observed: the median over every reconstructed point
    nothing = {**measures, "observed": np.zeros(shape, dtype=bool)}
    assert flag_points(options, reconstructed, nothing)[1]["residual_px"] == pytest.approx(
        max(1.5, 2.5 * np.median(measures["residual_px"]))
    )
