"""build_problem places the rows of tracks.csv column-wise: the same problem and rejections as row by row."""

import numpy as np
import pytest

import reconstruct.inputs as inputs
from dynrecon.errors import InputError
from sfm.cameras import CameraSet, FrameCamera, VideoCameras
from tracking.tracks import Tracks


def _cameras(rng):
    videos = []
    for v, frames in enumerate((range(0, 40, 2), range(5, 30), range(3), ())):
        posed = [
            FrameCamera(
                frame=f, K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), R=np.eye(3), t=rng.normal(size=3)
            )
            for f in frames
        ]
        rng.shuffle(posed)  # cameras.json need not list frames in order
        videos.append(VideoCameras(name=f"cam{v}", width=640, height=480, frames=posed))
    return CameraSet(videos=videos)


def _tracks(rng, n=600, repeat=False):
    rows = []
    for _ in range(n):
        video = f"cam{int(rng.integers(0, 4))}"
        x, y = rng.uniform(-150, 800), rng.uniform(-100, 600)  # some outside the image
        rows.append((video, int(rng.integers(0, 45)), f"p{int(rng.integers(0, 6))}", x, y))
    if not repeat:
        rows = list({(r[0], r[1], r[2]): r for r in rows}.values())
    return Tracks.from_rows(rows)


def _by_row(monkeypatch, *args):
    with monkeypatch.context() as patch:
        patch.setattr(inputs, "_frame_rows", lambda *_: None)
        return inputs.build_problem_checked(*args)


def _same(a, b):
    (pa, ra), (pb, rb) = a, b
    assert ra.to_json() == rb.to_json()
    for name in ("video_index", "frames", "times", "K", "R", "t", "uv"):
        assert getattr(pa, name).tobytes() == getattr(pb, name).tobytes()
    assert pa.point_names == pb.point_names and pa.video_names == pb.video_names


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_column_wise_rows_match_the_row_loop(monkeypatch, seed):
    rng = np.random.default_rng(seed)
    cameras, tracks = _cameras(rng), _tracks(rng)
    _same(inputs.build_problem_checked(cameras, tracks), _by_row(monkeypatch, cameras, tracks))
    names = ["p1", "p3", "other"]  # rows of other points are skipped
    _same(inputs.build_problem_checked(cameras, tracks, names), _by_row(monkeypatch, cameras, tracks, names))


def test_a_repeated_observation_in_memory_keeps_the_last_row(monkeypatch):
    rng = np.random.default_rng(5)
    cameras = _cameras(rng)
    tracks = Tracks.from_rows([("cam0", 2, "a", 10.0, 20.0), ("cam1", 5, "a", 1.0, 2.0), ("cam0", 2, "a", 30.0, 40.0)])
    problem, _ = inputs.build_problem_checked(cameras, tracks)
    _same((problem, _), _by_row(monkeypatch, cameras, tracks))
    assert problem.uv[list(problem.frames).index(2), 0].tolist() == [30.0, 40.0]


def test_an_unknown_video_names_its_first_row():
    rng = np.random.default_rng(6)
    tracks = Tracks.from_rows([("cam0", 2, "a", 1.0, 2.0), ("nope", 1, "a", 1.0, 2.0), ("nada", 1, "a", 1.0, 2.0)])
    with pytest.raises(InputError, match=r"row 1: video 'nope' is not in the cameras file"):
        inputs.build_problem_checked(_cameras(rng), tracks)
