"""Videos whose frames have no times but a rate (`register --fps`'s names: detections shared without their
videos): own time is frame / fps; the solve keeps the given rate where the tracks agree with it (offset-only
clocks) and fits each video's rate where one runs off it, as a phone's may."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruct import solve
from reconstruct.clocks.model import TimeSource
from sfm.cameras import CameraSet, FrameCamera, VideoCameras
from sfm.subject.synthetic import Truth, make_rig
from tracking.tracks import Tracks

GIVEN_FPS = 30.0


def _rig(true_fps: tuple[float, ...], timed: tuple[int, ...]) -> tuple[Tracks, CameraSet, Truth]:
    """A skeleton seen by 4 static cameras at `true_fps`, 20 s: its tracks, its true cameras with `fps`
    GIVEN_FPS and, for the videos `timed`, their frames' true decoder times (the others none: names), and the truth."""
    tracks, _, truth = make_rig(kind="skeleton", n_cameras=4, duration=20.0, fps=true_fps, distortion=False, seed=0)
    videos = np.asarray(tracks.video)
    cameras = CameraSet()
    for v, name in enumerate(truth.names):
        frames = int(np.max(np.asarray(tracks.frame)[videos == name])) + 1
        times = [k / true_fps[v] if v in timed else None for k in range(frames)]
        posed = [FrameCamera(frame=k, K=truth.K[v], R=truth.R[v], t=truth.t[v], time=times[k]) for k in range(frames)]
        cameras.videos.append(VideoCameras(name=name, width=1920, height=1080, fps=GIVEN_FPS, frames=posed))
    return tracks, cameras, truth


@pytest.mark.parametrize(
    ("true_fps", "timed", "model"),
    [
        ((30.0, 29.85, 30.0, 30.0), (), "affine"),  # cam1 runs 0.5 % slow: 50 ms behind its nominal times after 10 s
        ((30.0, 30.0, 30.0, 30.0), (), "offset"),  # a free rate where the given one holds trades offset against rate
        ((30.0, 29.85, 30.0, 30.0), (0, 2), "affine"),  # videos here (decoder times) beside names
    ],
)
def test_a_given_rate_is_tested_against_the_tracks(
    true_fps: tuple[float, ...], timed: tuple[int, ...], model: str
) -> None:
    tracks, cameras, truth = _rig(true_fps, timed)
    result = solve(cameras, tracks)
    assert result.report["clocks"]["given_rates"]["model"] == model
    assert result.report["clocks"]["model"] == model
    said = any(w.startswith("clock model: ") for w in result.report["clocks"]["warnings"])
    assert said is (model == "affine")  # a rate running off the given one is said, in the report too
    problem, times = result.problem, result.temporal.times
    sources = [c.time_source for c in result.temporal.clocks.videos]
    assert sources == [TimeSource.DECODER if v in timed else TimeSource.FPS for v in range(4)]
    # the seed solve's windows and the trust flag's jumps read the problem's times: the given rate's
    named = np.isin(problem.video_index, [v for v in range(4) if v not in timed])
    np.testing.assert_allclose(problem.times[named], problem.frames[named] / GIVEN_FPS)
    for v, name in enumerate(problem.video_names):
        rows = problem.video_index == v
        true = truth.offsets[v] + problem.frames[rows] / true_fps[v]  # cam0 is the reference: global = its own time
        # the 0.5 % slow camera's rate taken as given (offset-only clocks), its frames were 23 ms off (median)
        assert np.nanmedian(np.abs(times[rows] - true)) < 0.005, name


def test_decoder_times_are_kept_and_the_rates_tested_without_refinement() -> None:
    """A rate given through the API for a video with decoder times does not replace them (its decoder measured
    them); without refinement the rates are tested too (the clocks still time the written points)."""
    import dataclasses

    from reconstruct import SolveOptions
    from reconstruct.clocks.estimate import ClockOptions
    from reconstruct.temporal import Refinement, TemporalOptions

    tracks, cameras, _ = _rig((30.0, 29.85, 30.0, 30.0), timed=(0,))
    temporal = TemporalOptions(clocks=ClockOptions(fps={"cam0": 25.0}), refinement=Refinement.NONE)
    result = solve(cameras, tracks, dataclasses.replace(SolveOptions(recording=None), temporal=temporal))
    assert [c.time_source for c in result.temporal.clocks.videos] == [TimeSource.DECODER] + [TimeSource.FPS] * 3
    assert result.report["clocks"]["given_rates"]["model"] == "affine"
