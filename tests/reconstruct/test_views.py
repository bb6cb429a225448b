"""`views`: the videos that see a point near each instant. A point one video saw alone is flagged and left out of the
exports (a kick's ball, seen by one camera in one frame and by the other in all, came out metres off, unflagged)."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_motion import smooth_motion

import reconstruct
from reconstruct.outputs.export import measured_only
from reconstruct.views import SINGLE_VIEW, views_near
from simulation.simulate import SimulatedCapture, SimulationOptions, simulate_capture


def test_views_count_the_videos_within_two_frame_periods() -> None:
    # two videos at 10 fps, the second 0.05 s later; point 0 seen by both, point 1 by video 0 alone but for one frame
    times = np.concatenate([np.arange(10) * 0.1, np.arange(10) * 0.1 + 0.05])
    video = np.repeat([0, 1], 10)
    observed = np.ones((20, 2), dtype=bool)
    observed[10:, 1] = False
    observed[15, 1] = True  # video 1 sees point 1 at 0.55 s only
    views = views_near(video, times, observed)
    assert (views[:, 0] == 2).all()
    gap = np.abs(times - 0.55)
    clear = ~np.isclose(gap, 0.2)  # rows exactly two periods away may fall either side in floating point
    near = gap < 0.2
    assert (views[near & clear, 1] == 2).all() and (views[~near & clear, 1] == 1).all()


def test_a_video_of_one_frame_counts_its_own_observation() -> None:
    views = views_near(np.array([0, 0, 0, 1]), np.array([0.0, 0.1, 0.2, 0.1]), np.ones((4, 1), dtype=bool))
    assert views[:, 0].tolist() == [2, 2, 2, 2]
    alone = views_near(np.array([0, 1]), np.array([0.5, 0.5]), np.ones((2, 1), dtype=bool))  # one frame each
    assert alone[:, 0].tolist() == [2, 2]


def test_frames_without_a_time_use_their_neighbours_in_the_solve() -> None:
    video = np.array([0, 0, 1, 1])
    observed = np.array([[True], [True], [False], [True]])
    hood = np.array([[0, 2], [1, 3], [2, 0], [3, 1]])  # each frame and its neighbour in the other video
    views = views_near(video, np.full(4, np.nan), observed, hood)
    assert views[:, 0].tolist() == [1, 2, 1, 2]


@pytest.fixture(scope="module")
def one_view_point() -> tuple[SimulatedCapture, reconstruct.Reconstruction]:
    capture = simulate_capture(smooth_motion(120, 6), 120.0, SimulationOptions(seed=2, cameras=3))
    tracks = capture.tracks
    lone = np.array([p == "p0" and v != "cam0" for v, p in zip(tracks.video, tracks.point, strict=True)])
    kept_frame = int(np.asarray(tracks.frame)[lone][0])  # the other videos see p0 in one frame only
    keep = ~lone | (np.asarray(tracks.frame) == kept_frame) & (np.asarray(tracks.video) == tracks.video[lone.argmax()])
    result = reconstruct.solve(
        capture.cameras, tracks.take(np.flatnonzero(keep)), reconstruct.SolveOptions(recording=None)
    )
    return capture, result


def test_a_point_one_video_sees_alone_is_flagged(one_view_point) -> None:
    _, result = one_view_point
    p0 = result.problem.point_names.index("p0")
    views = result.trust.views[:, p0]
    single = views < SINGLE_VIEW
    assert 0.5 < single.mean() < 1.0  # all but the instants near the one frame the others see
    assert result.trust.flag[single, p0].all()
    others = np.delete(result.trust.views, p0, axis=1)
    assert (others >= SINGLE_VIEW).all()
    assert result.report["trust"]["single_view"] == int(single.sum())
    assert "views < 2" in result.report["trust"]["rule"]


def test_exports_leave_single_view_positions_out(one_view_point, caplog: pytest.LogCaptureFixture) -> None:
    _, result = one_view_point
    points = result.points
    p0 = points.point_names.index("p0")
    exported = measured_only(points)
    single = points.extra["views"][:, p0] < SINGLE_VIEW
    assert np.isnan(exported.xyz[single, p0]).all() and np.isfinite(exported.xyz[~single, p0]).all()
    assert np.array_equal(np.delete(exported.xyz, p0, axis=1), np.delete(points.xyz, p0, axis=1))
    assert "left out" in caplog.text and "p0" in caplog.text


def test_an_export_that_loses_a_whole_point_says_so(caplog: pytest.LogCaptureFixture) -> None:
    from reconstruct.outputs.points import FramePoints

    xyz = np.ones((4, 2, 3))
    views = np.array([[2.0, 1.0]] * 4)  # point b: never a second view
    points = FramePoints(
        videos=["a", "a", "b", "b"],
        frames=np.array([0, 1, 0, 1]),
        point_names=["a", "b"],
        xyz=xyz,
        observed=np.ones((4, 2), dtype=bool),
        extra={"views": views},
    )
    kept = measured_only(points)
    assert np.isnan(kept.xyz[:, 1]).all() and np.isfinite(kept.xyz[:, 0]).all()
    assert "no two videos ever saw b near the same instant: it is empty in the export" in caplog.text
    caplog.clear()
    measured_only(kept)  # a second pass (the TRC after the C3D) has nothing to say
    assert not caplog.text


def test_a_video_without_a_clock_counts_for_the_timed_frames_through_their_neighbours() -> None:
    # video 1's clock is unknown: the timed frames of video 0 see it through W, as video 1's frames see video 0
    video = np.array([0, 0, 1, 1])
    times = np.array([0.0, 0.1, np.nan, np.nan])
    observed = np.ones((4, 1), dtype=bool)
    hood = np.array([[0, 2], [1, 3], [2, 0], [3, 1]])
    assert views_near(video, times, observed, hood)[:, 0].tolist() == [2, 2, 2, 2]
    assert views_near(video, times, observed)[:, 0].tolist() == [1, 1, 1, 1]  # without W: each its own
