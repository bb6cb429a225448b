"""Videos the tracks do not link: two groups that share no point are refused (each is solved on its own with
`--videos`), and a video with no observation is left out of the solve instead of failing every other's clock."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from synthetic_motion import smooth_motion

import reconstruct
from dynrecon.errors import InputError
from simulation.simulate import SimulatedCapture, SimulationOptions, simulate_capture
from tracking.tracks import Tracks, join_tracks


@pytest.fixture(scope="module")
def capture() -> SimulatedCapture:
    return simulate_capture(smooth_motion(60, 6), 120.0, SimulationOptions(seed=5, cameras=4))


def _renamed(tracks: Tracks, videos: set[str]) -> Tracks:
    """The points of `videos` under other names: those videos then share no point with the rest."""
    points = [f"other_{p}" if v in videos else p for v, p in zip(tracks.video, tracks.point, strict=True)]
    return dataclasses.replace(tracks, point=points)


def test_two_groups_that_share_no_point_are_refused_and_each_solves_alone(capture: SimulatedCapture) -> None:
    tracks = _renamed(capture.tracks, {"cam2", "cam3"})
    options = reconstruct.SolveOptions(recording=None)
    with pytest.raises(InputError, match="2 groups that share no tracked point") as refused:
        reconstruct.solve(capture.cameras, tracks, options)
    assert "cam0, cam1 (points" in str(refused.value) and "--videos cam0,cam1" in str(refused.value)

    alone = reconstruct.solve(capture.cameras, tracks, dataclasses.replace(options, videos=("cam0", "cam1")))
    assert sorted(set(alone.points.videos)) == ["cam0", "cam1"]
    truth = capture.truth.xyz[np.isin(np.asarray(capture.truth.videos), ["cam0", "cam1"])]
    error = np.linalg.norm(alone.points.xyz - truth, axis=-1)
    assert np.nanmedian(error) < 1.0  # mm: the group's own solve is exact


def test_videos_names_an_unknown_video(capture: SimulatedCapture) -> None:
    with pytest.raises(InputError, match="--videos names cam9, not in the cameras file"):
        reconstruct.solve(
            capture.cameras, capture.tracks, reconstruct.SolveOptions(recording=None, videos=("cam0", "cam9"))
        )


def test_a_video_without_observations_is_left_out(capture: SimulatedCapture, caplog: pytest.LogCaptureFixture) -> None:
    tracks = capture.tracks.of_videos(["cam1", "cam2", "cam3"])  # cam0, the first video, has none
    with caplog.at_level(logging.WARNING):
        result = reconstruct.solve(capture.cameras, tracks, reconstruct.SolveOptions(recording=None))
    assert "no observation of video(s) cam0" in caplog.text
    assert "cam0" not in set(result.points.videos)
    clocks = result.temporal.clocks
    assert clocks.reference == "cam1" and len(clocks.videos) == 3
    assert all(clock.identified for clock in clocks.videos)  # before: none linked to cam0, the reference


def test_groups_are_solved_together_where_the_cameras_file_gives_every_clock(
    capture: SimulatedCapture, caplog: pytest.LogCaptureFixture
) -> None:
    """A synchronized lab whose cameras see different sides (DeepFly3D's fly): the declared clocks tie the groups."""
    tracks = _renamed(capture.tracks, {"cam2", "cam3"})
    videos = [dataclasses.replace(video, clock_offset=0.0) for video in capture.cameras.videos]  # one clock here
    cameras = dataclasses.replace(capture.cameras, videos=videos)
    with caplog.at_level(logging.WARNING):
        result = reconstruct.solve(cameras, tracks, reconstruct.SolveOptions(recording=None))
    assert "2 groups that share no tracked point" in caplog.text and "gives every clock offset" in caplog.text
    names = np.array(result.points.point_names)
    truth = capture.truth.xyz[:, [int(name.split("p")[-1]) for name in names]]
    error = np.linalg.norm(result.points.xyz - truth, axis=-1)
    assert np.nanmedian(error) < 1.0  # mm


def test_videos_selects_by_the_cameras_names_whatever_the_tracks_call_them(capture: SimulatedCapture) -> None:
    tracks = _renamed(capture.tracks, {"cam2", "cam3"})
    tracks = dataclasses.replace(tracks, video=[f"{name}.mp4" for name in tracks.video])  # matched to cam0, ...
    options = reconstruct.SolveOptions(recording=None, videos=("cam0", "cam1"))
    assert sorted(set(reconstruct.solve(capture.cameras, tracks, options).points.videos)) == ["cam0", "cam1"]
    with pytest.raises(InputError, match="--videos names 1 video: a solve needs at least two"):
        reconstruct.solve(capture.cameras, tracks, dataclasses.replace(options, videos=("cam0",)))


def test_a_stray_detection_does_not_link_two_groups(capture: SimulatedCapture) -> None:
    tracks = _renamed(capture.tracks, {"cam2", "cam3"})
    stray = Tracks.from_rows([("cam0", int(capture.tracks.frame[0]), "other_p0", 500.0, 500.0)])
    tracks = join_tracks(tracks, stray)  # one false detection of the other group's point
    with pytest.raises(InputError, match="2 groups that share no tracked point"):
        reconstruct.solve(capture.cameras, tracks, reconstruct.SolveOptions(recording=None))


def test_a_video_that_shares_no_point_is_left_out(capture: SimulatedCapture, caplog: pytest.LogCaptureFixture) -> None:
    tracks = _renamed(capture.tracks, {"cam3"})
    with caplog.at_level(logging.WARNING):
        result = reconstruct.solve(capture.cameras, tracks, reconstruct.SolveOptions(recording=None))
    assert "video(s) cam3 share no tracked point" in caplog.text
    assert sorted(set(result.points.videos)) == ["cam0", "cam1", "cam2"]
    assert all(clock.identified for clock in result.temporal.clocks.videos)
