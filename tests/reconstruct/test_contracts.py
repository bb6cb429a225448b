import json

import numpy as np
import pytest

from dynrecon.errors import InputError
from reconstruct.inputs import build_problem
from reconstruct.outputs.points import (
    FramePoints,
    Sequencing,
    read_points,
    read_sequencing,
    write_points,
    write_sequencing,
)
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras, write_cameras
from tracking.tracks import Tracks, read_tracks, write_tracks


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _cameras(rng=None):
    rng = rng or np.random.default_rng(0)
    K = np.array([[900.0, 0, 320], [0, 910, 240], [0, 0, 1]])
    return CameraSet(
        videos=[
            VideoCameras(
                name="a",
                width=640,
                height=480,
                fps=30.0,
                frames=[
                    FrameCamera(frame=0, time=0.0, K=K, R=_rotation(rng), t=rng.normal(size=3)),
                    FrameCamera(
                        frame=3,
                        time=0.1,
                        K=K,
                        R=_rotation(rng),
                        t=rng.normal(size=3),
                        dist=np.array([0.1, -0.01, 0.0, 0.0, 0.001]),
                    ),
                ],
            ),
            VideoCameras(
                name="b",
                width=640,
                height=480,
                fps=None,
                frames=[FrameCamera(frame=1, K=K, R=_rotation(rng), t=rng.normal(size=3))],
            ),
        ]
    )


def test_cameras_round_trip(tmp_path):
    cameras = _cameras()
    back = read_cameras(write_cameras(tmp_path / "cameras.json", cameras))
    for video, video_back in zip(cameras.videos, back.videos, strict=True):
        assert (video.name, video.width, video.height, video.fps) == (
            video_back.name,
            video_back.width,
            video_back.height,
            video_back.fps,
        )
        for frame, frame_back in zip(video.frames, video_back.frames, strict=True):
            assert frame.frame == frame_back.frame and frame.time == frame_back.time
            for key in ("K", "R", "t"):
                np.testing.assert_array_equal(getattr(frame, key), getattr(frame_back, key))
            assert (frame.dist is None) == (frame_back.dist is None)


def test_tracks_round_trip_keeps_extra_columns(tmp_path):
    tracks = Tracks.from_rows(
        [("a", 0, "head", 1.25, 2.5), ("b", 1, "head", 3.0, 4.0), ("a", 0, "foot", 5, 6)],
        source=["label", "track", "label"],
        score=["1", "0.5", "1"],
    )
    back = read_tracks(write_tracks(tmp_path / "tracks.csv", tracks))
    rows = sorted(zip(back.video, back.frame.tolist(), back.point, back.xy.tolist(), back.extra["source"], strict=True))
    expected = sorted(
        zip(tracks.video, tracks.frame.tolist(), tracks.point, tracks.xy.tolist(), tracks.extra["source"], strict=True)
    )
    assert rows == expected


def test_points_and_sequencing_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(3, 2, 3))
    xyz[1, 0] = np.nan
    points = FramePoints(
        videos=["a", "a", "b"],
        frames=np.array([0, 3, 1]),
        point_names=["head", "foot"],
        xyz=xyz,
        observed=np.array([[1, 1], [0, 1], [1, 0]], bool),
        extra={"time": rng.normal(size=(3, 2))},
    )
    back = read_points(write_points(tmp_path / "points3d.csv", points))
    np.testing.assert_array_equal(back.xyz, xyz)
    np.testing.assert_array_equal(back.observed, points.observed)
    np.testing.assert_array_equal(back.extra["time"], points.extra["time"])
    header = (tmp_path / "points3d.csv").read_text().splitlines()[0]
    assert header == "video,frame,point,x,y,z,observed,time"
    sequencing = Sequencing(
        videos=["a", "a", "b"],
        frames=np.array([0, 3, 1]),
        neighbours=[np.array([2]), np.array([2, 0]), np.array([1])],
        weights=[np.array([1.0]), np.array([0.25, 0.75]), np.array([1.0])],
    )
    seq_back = read_sequencing(write_sequencing(tmp_path / "sequencing.json", sequencing))
    for a, b in zip(sequencing.weights, seq_back.weights, strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(sequencing.neighbours, seq_back.neighbours, strict=True):
        np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------------------------------ bad input


def _write_json(path, data):
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d["videos"][0]["frames"][0].__setitem__("R", [[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "not a rotation"),
        (lambda d: d["videos"][0]["frames"][0].__setitem__("t", [0, float("nan"), 0]), "NaN or infinity"),
        (lambda d: d["videos"][0]["frames"][0].__setitem__("K", [[1, 0], [0, 1]]), "shape"),
        (lambda d: d["videos"][0].pop("width"), 'missing key "width"'),
        (lambda d: d["videos"][1].__setitem__("name", "a"), "appears twice"),
        (lambda d: d["videos"][0]["frames"][1].__setitem__("frame", 0), "frame appears twice"),
        (lambda d: d["videos"][0]["frames"][0].__setitem__("frame", -1), "non-negative"),
    ],
)
def test_bad_cameras_name_the_video_and_frame(tmp_path, mutate, message):
    path = write_cameras(tmp_path / "cameras.json", _cameras())
    data = json.loads(path.read_text())
    mutate(data)
    path.write_text(json.dumps(data).replace("NaN", "NaN"))
    with pytest.raises(InputError, match=message) as error:
        read_cameras(path)
    assert str(path) in str(error.value)
    assert "\n" not in str(error.value)


def test_malformed_json_names_line_and_column(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text('{"videos": [\n  {"name": "a",,}\n]}')
    with pytest.raises(InputError, match=r"cameras.json:2:\d+: invalid JSON"):
        read_cameras(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "file is empty"),
        ("video,frame,x,y\na,0,1,2\n", "lacks column"),
        ("video,frame,point,x,y\na,zero,p,1,2\n", "line 2: frame 'zero' is not an integer"),
        ("video,frame,point,x,y\na,0,p,nan,2\n", "line 2: x, y = nan, 2.0 is not finite"),
        ("video,frame,point,x,y\na,0,p,inf,2\n", "not finite"),
        (
            "video,frame,point,x,y\na,0,p,1,2\na,1,p,1,2\na,0,p,3,4\n",
            r"line 4: duplicate observation .* \(first on line 2\)",
        ),
        ("video,frame,point,x,y\na,0,p,1\n", "line 2: expected 5 fields"),
    ],
)
def test_bad_tracks_name_the_line(tmp_path, text, message):
    path = tmp_path / "tracks.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_tracks(path)


def test_unknown_video_in_tracks_is_an_error_and_unposed_frames_a_warning(tmp_path, caplog):
    cameras = _cameras()
    path = tmp_path / "tracks.csv"
    path.write_text("video,frame,point,x,y\na,0,p,1,2\nb,1,p,3,4\na,7,p,1,1\n")
    problem = build_problem(cameras, read_tracks(path))
    assert int(problem.observed.sum()) == 2
    assert any("without a pose" in r.message and "line 4" in r.message for r in caplog.records)
    path.write_text("video,frame,point,x,y\na,0,p,1,2\nzz,1,p,3,4\n")
    with pytest.raises(InputError, match="line 3: video 'zz' is not in the cameras file"):
        build_problem(cameras, read_tracks(path))
