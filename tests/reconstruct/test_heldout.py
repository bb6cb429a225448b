"""Leave one video out (reconstruct/heldout.py): a wrong clock predicts its video's rays from the other videos worse
than the true clock does, also where it moves the video out of the others' time span and so fits every ray alone."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from synthetic_motion import simulated_phones

from reconstruct.free_times import reprojection_px
from reconstruct.heldout import MAX_POINTS, MIN_POINTS, heldout_px, on_most_observed, point_budget
from reconstruct.stage import SolveOptions, solve
from reconstruct.tracks_path import start_points
from reconstruct.trajectory import RefineOptions, refine
from sfm.cameras import read_cameras


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    sim = simulated_phones(tmp_path_factory.mktemp("phones"), noise_px=1.0)
    return solve(read_cameras(Path(sim) / "cameras.json"), Path(sim) / "tracks.csv", SolveOptions(recording=None))


def _shifted(times: np.ndarray, moved: np.ndarray, seconds: float) -> np.ndarray:
    out = times.copy()
    out[moved] += seconds
    return out


def test_a_wrong_clock_predicts_its_video_worse(solved) -> None:  # type: ignore[no-untyped-def]
    problem, times = solved.problem, solved.temporal.times
    moved = problem.video_index == 1
    right = heldout_px(problem, times, RefineOptions())
    wrong = heldout_px(problem, _shifted(times, moved, 0.2), RefineOptions())

    assert np.isfinite(right.per_video_px).all()
    assert wrong.per_video_px[1] > 2 * right.per_video_px[1]
    assert wrong.median_px > 1.5 * right.median_px
    # every observed ray of every video is predicted once
    assert right.rays_px.size == int(problem.observed.sum())


def test_a_clock_that_moves_a_video_out_of_the_others_span_is_caught(solved) -> None:  # type: ignore[no-untyped-def]
    """Moved past the others' span its rays are met by a trajectory of their own (no residual), so the in-sample
    residual cannot say it is wrong; held out, they are predicted by the others' trajectories and miss."""
    problem, times = solved.problem, solved.temporal.times
    moved = problem.video_index == 1
    span = float(np.nanmax(times) - np.nanmin(times))
    far = _shifted(times, moved, 0.8 * span)
    in_sample = {
        name: float(np.nanmedian(reprojection_px(problem, refine(problem, start_points(problem, t), t).points)))
        for name, t in (("right", times), ("far", far))
    }
    assert in_sample["far"] < 1.5 * in_sample["right"]

    right = heldout_px(problem, times, RefineOptions())
    wrong = heldout_px(problem, far, RefineOptions())
    assert wrong.median_px > 2 * right.median_px


def test_long_captures_use_fewer_of_theon_most_observed_points(solved) -> None:  # type: ignore[no-untyped-def]
    problem = solved.problem
    assert point_budget(100) == MAX_POINTS and point_budget(10**6) == MIN_POINTS
    assert MIN_POINTS <= point_budget(4000) <= MAX_POINTS
    counts = problem.observed.sum(axis=0)
    fewer = on_most_observed(problem, 3)
    assert fewer.num_points == 3 and fewer.num_frames == problem.num_frames
    assert sorted(fewer.observed.sum(axis=0)) == sorted(counts)[-3:]
    assert on_most_observed(problem, problem.num_points) is problem


def test_a_point_only_one_other_video_sees_is_not_predicted(solved) -> None:  # type: ignore[no-untyped-def]
    """Left out of one of the two videos that see it, a point has one view left: no depth, no prediction."""
    problem, times = solved.problem, solved.temporal.times
    uv = problem.uv.copy()
    uv[problem.video_index == 2, 0] = np.nan  # point 0 seen by videos 0 and 1 only
    two_views = replace(problem, uv=uv)

    held = heldout_px(two_views, times, RefineOptions())

    lost = int(two_views.observed[:, 0].sum())  # its rays in videos 0 and 1, each left out with one view left
    assert held.rays_px.size == int(two_views.observed.sum()) - lost
    assert held.median_px < 2 * heldout_px(problem, times, RefineOptions()).median_px
