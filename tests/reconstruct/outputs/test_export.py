"""TRC / C3D exports: round trips through the project's mocap reader and ezc3d, and the global frame order."""

from __future__ import annotations

import os

import numpy as np
import pytest

from dynrecon.errors import InputError
from reconstruct.outputs.export import (
    TIMING_NOTE,
    OrderSource,
    global_order,
    write_c3d_export,
    write_trc_export,
)
from reconstruct.outputs.mocap import read_mocap
from reconstruct.outputs.points import FramePoints, Sequencing
from sfm.cameras import CameraSet, FrameCamera, VideoCameras


def _interleaved(num_videos: int = 3, per_video: int = 8, seed: int = 0) -> tuple[FramePoints, np.ndarray]:
    """Frames of `num_videos` videos interleaved in true time (grouped by video in the file), and true times."""
    rng = np.random.default_rng(seed)
    videos, frames, times = [], [], []
    for v in range(num_videos):
        for f in range(per_video):
            videos.append(f"cam{v}")
            frames.append(f)
            times.append(f * num_videos + v)  # true global sample index
    true_time = np.array(times, dtype=float)
    xyz = rng.normal(size=(len(videos), 4, 3)) * 500.0
    xyz[2, 1] = np.nan  # one unreconstructed point
    points = FramePoints(
        videos=videos,
        frames=np.array(frames),
        point_names=["a", "b", "c", "d"],
        xyz=xyz,
        observed=np.ones((len(videos), 4), bool),
    )
    return points, true_time


def test_trc_round_trip_in_order(tmp_path):
    points, true_time = _interleaved()
    order = np.argsort(true_time)
    path = write_trc_export(points, order, 90.0, tmp_path / "out.trc")
    back = read_mocap(path)
    assert back.marker_names == points.point_names
    assert back.rate == 90.0
    np.testing.assert_allclose(back.times, np.arange(len(order)) / 90.0)
    expected = points.xyz[order]
    assert np.array_equal(np.isnan(back.xyz), np.isnan(expected))
    np.testing.assert_allclose(back.xyz, expected, rtol=0, atol=1e-9)


def test_trc_units_metres(tmp_path):
    points, _ = _interleaved()
    points.xyz = points.xyz / 1000.0  # a world in metres
    back = read_mocap(write_trc_export(points, None, 30.0, tmp_path / "m.trc", units="m"))
    np.testing.assert_allclose(back.xyz, points.xyz * 1000.0, atol=1e-9)  # the reader converts to mm


def test_c3d_round_trip_with_sources(tmp_path):
    import ezc3d

    points, true_time = _interleaved()
    order = np.argsort(true_time)
    path = write_c3d_export(points, order, 90.0, tmp_path / "out.c3d")
    back = read_mocap(path)
    assert back.marker_names == points.point_names
    assert back.rate == pytest.approx(90.0)
    expected = points.xyz[order]
    assert np.array_equal(np.isnan(back.xyz), np.isnan(expected))
    np.testing.assert_allclose(back.xyz, expected, rtol=1e-6, atol=1e-3)  # C3D stores float32
    c3d = ezc3d.c3d(str(path))
    group = c3d["parameters"]["DYNRECON"]
    assert group["TIMING"]["value"][0] == TIMING_NOTE
    assert list(group["VIDEOS"]["value"]) == [points.videos[i] for i in order]
    assert [int(f) for f in group["FRAMES"]["value"]] == [int(points.frames[i]) for i in order]
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # like a plain open(), not mkstemp's 0600
    assert [p.name for p in tmp_path.iterdir()] == ["out.c3d"]  # no scratch files left behind


def test_bad_order_and_rate(tmp_path):
    points, _ = _interleaved()
    with pytest.raises(InputError, match="frame indices"):
        write_trc_export(points, np.array([0, 99]), 30.0, tmp_path / "x.trc")
    with pytest.raises(InputError, match="rate"):
        write_c3d_export(points, None, 0.0, tmp_path / "x.c3d")
    with pytest.raises(InputError, match="units"):
        write_trc_export(points, None, 30.0, tmp_path / "x.trc", units="furlong")


def test_order_by_decoder_time(tmp_path):
    points, _ = _interleaved(per_video=4)
    videos = []
    for v in range(3):
        frames = [
            FrameCamera(frame=f, time=f / 30.0 + 0.001 * v, K=np.eye(3), R=np.eye(3), t=np.zeros(3)) for f in range(4)
        ]
        videos.append(VideoCameras(name=f"cam{v}", width=10, height=10, fps=30.0, frames=frames))
    order, source = global_order(points, CameraSet(videos=videos))
    assert source is OrderSource.TIME
    assert [(points.videos[i], int(points.frames[i])) for i in order[:4]] == [
        ("cam0", 0),
        ("cam1", 0),
        ("cam2", 0),
        ("cam0", 1),
    ]
    # Without times for every frame, and without sequencing, the file order stays.
    videos[0].frames[0].time = None
    order, source = global_order(points, CameraSet(videos=videos))
    assert source is OrderSource.FILE
    assert np.array_equal(order, np.arange(points.num_frames))


def test_order_from_sequencing_recovers_time():
    """Neighbours linking each frame to the other videos' frames nearest in true time give back the true order."""
    points, true_time = _interleaved(per_video=10)
    neighbours, weights = [], []
    for i in range(points.num_frames):
        others = np.flatnonzero(np.array(points.videos) != points.videos[i])
        nearest = others[np.argsort(np.abs(true_time[others] - true_time[i]))[:2]]
        neighbours.append(nearest)
        weights.append(np.array([0.5, 0.5]))
    sequencing = Sequencing(videos=points.videos, frames=points.frames, neighbours=neighbours, weights=weights)
    order, source = global_order(points, None, sequencing)
    assert source is OrderSource.SEQUENCING
    recovered = true_time[order]
    # A spectral order is exact up to local swaps: every row is within one sample of its true rank.
    assert np.abs(np.argsort(np.argsort(recovered)) - np.arange(len(order))).max() <= 1
    assert np.corrcoef(recovered, np.arange(len(order)))[0, 1] > 0.99


def _with_clocks(points: FramePoints, times: np.ndarray, std: float = 0.002) -> Sequencing:
    frames = [
        {"video": v, "frame": int(f), "own_time": float(t), "time": float(t), "time_std": std}
        for v, f, t in zip(points.videos, points.frames, times, strict=True)
    ]
    return Sequencing(
        videos=points.videos,
        frames=points.frames,
        neighbours=[np.zeros(0, int)] * points.num_frames,
        weights=[np.zeros(0)] * points.num_frames,
        extra={"clocks": {"frames": frames}},
    )


def test_recovered_clocks_order_the_frames_before_decoder_times():
    points, true_time = _interleaved()
    order, source = global_order(points, None, _with_clocks(points, true_time / 90.0))
    assert source is OrderSource.CLOCKS
    np.testing.assert_array_equal(order, np.argsort(true_time))


def test_trc_on_the_clock_is_a_uniform_resampling_of_linear_motion(tmp_path):
    """Frames at uneven global times of a point moving linearly: the uniform resampling is exact, and a gap
    longer than MAX_GAP_FACTOR spacings stays empty."""
    rng = np.random.default_rng(3)
    times = np.arange(60) / 60.0 + rng.uniform(-0.004, 0.004, 60)  # two videos' frames, jittered
    times[30:] += 1.0  # a 1 s hole in the capture
    velocity = np.array([100.0, -50.0, 20.0])
    xyz = (times[:, None] * velocity)[:, None, :].repeat(2, axis=1)
    xyz[5, 1] = np.nan
    points = FramePoints(
        videos=["a", "b"] * 30, frames=np.arange(60), point_names=["p", "q"], xyz=xyz, observed=np.ones((60, 2), bool)
    )
    back = read_mocap(write_trc_export(points, None, 50.0, tmp_path / "c.trc", times=times))
    grid = back.times
    np.testing.assert_allclose(np.diff(grid), 1 / 50.0, atol=1e-6)
    hole = (grid + times[0] > times[29] + 1e-9) & (grid + times[0] < times[30] - 1e-9)
    assert hole.any() and np.all(np.isnan(back.xyz[hole]))
    expected = (grid + times[0])[:, None] * velocity
    ok = ~hole
    np.testing.assert_allclose(back.xyz[ok, 0], expected[ok], atol=1e-6)
    np.testing.assert_allclose(back.xyz[ok, 1], expected[ok], atol=1e-6)


def test_nearly_synchronized_videos_export_every_instant(tmp_path):
    """Two 30 fps videos 1 ms apart: their pooled frame times alternate 1 ms and 32 ms gaps, but the gap that may
    not be bridged is measured in the videos' own frame periods, so every grid time between frames is filled."""
    own = np.arange(30) / 30.0
    times = np.concatenate([own, own + 0.001])
    xyz = (1.0 + times[:, None] * np.array([1.0, 2.0, 3.0]))[:, None, :]  # off the origin (TRC: 0 0 0 = empty)
    points = FramePoints(
        videos=["a"] * 30 + ["b"] * 30,
        frames=np.concatenate([np.arange(30), np.arange(30)]),
        point_names=["p"],
        xyz=xyz,
        observed=np.ones((60, 1), bool),
    )
    back = read_mocap(write_trc_export(points, None, 60.0, tmp_path / "s.trc", times=times))
    assert len(back.times) > 50 and not np.isnan(back.xyz).any()


def test_a_video_reconstructed_on_few_frames_bridges_no_gap(tmp_path):
    """Video a at 30 fps loses the point for 3 s; video b has it on two frames only (1 s and 9 s): b's own frame
    step (8 s) must not let the export bridge a's gap."""
    own = np.arange(300) / 30.0
    a = own[(own < 4.0) | (own >= 7.0)]
    times = np.concatenate([a, [1.0 + 1e-3, 9.0 + 1e-3]])
    xyz = (1.0 + times[:, None] * np.array([1.0, 2.0, 3.0]))[:, None, :]
    points = FramePoints(
        videos=["a"] * len(a) + ["b"] * 2,
        frames=np.concatenate([np.arange(len(a)), [30, 270]]),
        point_names=["p"],
        xyz=xyz,
        observed=np.ones((len(times), 1), bool),
    )
    back = read_mocap(write_trc_export(points, None, 30.0, tmp_path / "g.trc", times=times))
    clock = back.times + times.min()
    inside = (clock > 4.05) & (clock < 6.95)
    assert inside.sum() > 80 and np.isnan(back.xyz[inside]).all()


def test_c3d_on_the_clock_carries_the_uncertainty_note(tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    from reconstruct.outputs.export import clock_note

    points, true_time = _interleaved()
    sequencing = _with_clocks(points, true_time / 90.0, std=0.004)
    note = clock_note(sequencing)
    assert "4.0 ms" in note
    path = write_c3d_export(points, None, 90.0, tmp_path / "c.c3d", times=true_time / 90.0, note=note)
    c3d = ezc3d.c3d(str(path))
    assert c3d["parameters"]["DYNRECON"]["TIMING"]["value"] == [note]
    assert c3d["data"]["points"].shape[2] == len(points.videos)  # 24 frames over 23/90 s at 90 Hz
