"""The isolated-spike screen (reconstruct/screen.py): false detections off their own track are set aside, real
motion is not, and the solve's report counts them."""

from __future__ import annotations

import dataclasses

import numpy as np
from synthetic_motion import synthetic_problem

from reconstruct.screen import find_spikes, remove_spikes


def test_clean_and_noisy_tracks_have_no_spikes() -> None:
    for noise in (0.0, 1.0):
        problem, _ = synthetic_problem(noise_px=noise)
        assert not find_spikes(problem).any()


def test_false_detections_far_off_their_track_are_found() -> None:
    problem, _ = synthetic_problem()
    rng = np.random.default_rng(3)
    observed = np.argwhere(problem.observed)
    chosen = observed[rng.choice(len(observed), size=20, replace=False)]
    uv = problem.uv.copy()
    for f, p in chosen:
        # far from the true position: at least a fifth of the image away, anywhere else in it
        while True:
            candidate = rng.uniform(0, 1000, size=2)
            if np.linalg.norm(candidate - uv[f, p]) > 300:
                break
        uv[f, p] = candidate
    dirty = dataclasses.replace(problem, uv=uv)
    spikes = find_spikes(dirty)
    hit = np.zeros_like(spikes)
    hit[chosen[:, 0], chosen[:, 1]] = True
    assert not (spikes & ~hit).any()  # no clean observation set aside
    # the ends of a track are checked against an extrapolation, with a looser limit: most, not all, are found
    assert spikes.sum() >= 16
    cleaned, count = remove_spikes(dirty)
    assert count == spikes.sum() and np.isnan(cleaned.uv[spikes]).all()


def test_a_real_bounce_is_not_a_spike() -> None:
    """A ball hitting the floor: one frame at the bottom, its neighbours both higher; ~60 px deep at 30 fps."""
    problem, _ = synthetic_problem()
    rows = np.flatnonzero(problem.video_index == 0)
    rows = rows[np.argsort(problem.frames[rows])]
    uv = problem.uv.copy()
    uv[rows[10], 0] = uv[rows[10], 0] + np.array([0.0, 60.0])
    assert not find_spikes(dataclasses.replace(problem, uv=uv))[rows[10], 0]


def test_points_leaving_their_tracks_together_are_real_motion_but_a_whole_frame_jump_is_not() -> None:
    """A kick at a low frame rate: several points of one frame off their lines at once are kept; a frame where
    every point jumps (the detector took another person) is still set aside."""
    problem, _ = synthetic_problem()
    rows = np.flatnonzero(problem.video_index == 0)
    rows = rows[np.argsort(problem.frames[rows])]
    kick, swap = rows[10], rows[20]
    seen_kick = np.flatnonzero(problem.observed[kick])
    seen_swap = np.flatnonzero(problem.observed[swap])
    assert len(seen_kick) >= 6
    uv = problem.uv.copy()
    legs = seen_kick[: max(4, len(seen_kick) // 2)]
    uv[kick, legs] += np.array([300.0, 0.0])
    uv[swap, seen_swap] += np.array([0.0, 300.0])
    spikes = find_spikes(dataclasses.replace(problem, uv=uv))
    assert not spikes[kick].any()
    assert spikes[swap, seen_swap].sum() >= 0.75 * len(seen_swap)
