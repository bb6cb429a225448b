from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.errors import DynreconError, InputError
from reconstruct.outputs.mocap import Mocap, read_mocap, write_trc
from reconstruct.outputs.points import read_points
from sfm.cameras import read_cameras
from simulation.simulate import (
    SimulatedCapture,
    SimulationOptions,
    assign_cameras,
    project,
    run,
    simulate_capture,
    simulate_mocap,
)
from tracking.tracks import read_tracks


def walking_body(frames: int = 240, markers: int = 12, rate: float = 120.0, seed: int = 1) -> np.ndarray:
    """A 1.7 m tall, Z-up 'body' of markers swinging while it walks along x, (T, M, 3) mm."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate
    base = np.stack(
        [rng.uniform(-250, 250, markers), rng.uniform(-150, 150, markers), rng.uniform(0, 1700, markers)], axis=1
    )
    phase = rng.uniform(0, 6, markers)[:, None]
    swing = rng.uniform(50, 200, (markers, 3)) * np.sin(2 * np.pi * 1.2 * t[:, None, None] + phase)
    walk = np.stack([800 * t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    return base[None] + swing + walk[:, None]


def captures_by_time(capture: SimulatedCapture) -> tuple[np.ndarray, np.ndarray]:
    """(video index, time) of every capture, sorted by time."""
    truth = capture.truth
    times = truth.extra["time"][:, 0]
    order = np.argsort(times, kind="stable")
    return np.array([int(v[3:]) for v in truth.videos])[order], times[order]


def reprojection(capture: SimulatedCapture) -> tuple[np.ndarray, np.ndarray]:
    """Projections of the truth of every track row, and the track's pixels, both (N, 2)."""
    cams = {(v.name, f.frame): f for v in capture.cameras.videos for f in v.frames}
    index = capture.truth.index()
    names = {n: i for i, n in enumerate(capture.truth.point_names)}
    projected = np.empty((len(capture.tracks), 2))
    for row in range(len(capture.tracks)):
        key = (capture.tracks.video[row], int(capture.tracks.frame[row]))
        cam = cams[key]
        point = capture.truth.xyz[index[key], names[capture.tracks.point[row]]]
        projected[row] = project(point, cam.K, cam.R, cam.t)[0]
    return projected, capture.tracks.xy


def test_protocol_noise_free() -> None:
    xyz = walking_body()
    capture = simulate_capture(xyz, 120.0, SimulationOptions(seed=3))
    truth = capture.truth
    # Each capture exactly once, with its true time and true positions.
    video_of, times = captures_by_time(capture)
    np.testing.assert_allclose(times, np.arange(240) / 120.0)
    order = np.argsort(truth.extra["time"][:, 0], kind="stable")
    np.testing.assert_array_equal(truth.xyz[order], xyz)
    assert capture.cameras.num_frames == 240
    # Never the same camera twice in a row; all four used about equally.
    assert not np.any(video_of[1:] == video_of[:-1])
    assert np.all(np.bincount(video_of, minlength=4) > 40)
    # Frame numbers are 0..n-1 within each video, in time order, with the time in cameras.json.
    for video in capture.cameras.videos:
        assert [f.frame for f in video.frames] == list(range(len(video.frames)))
        assert np.all(np.diff([f.time for f in video.frames]) > 0)
        assert video.width == video.height == 1000 and video.fps is None
    # Noise-free: the tracks are exactly the projections of the truth, all inside the image.
    assert len(capture.tracks) == xyz.shape[0] * xyz.shape[1] and truth.observed.all()
    projected, tracked = reprojection(capture)
    np.testing.assert_allclose(tracked, projected, atol=1e-9)
    assert tracked.min() >= 0 and tracked.max() <= 999


def test_cameras_are_static_around_the_centroid_at_twice_the_scale() -> None:
    xyz = walking_body()
    capture, rig = simulate_mocap(
        Mocap(xyz=xyz, rate=120.0, marker_names=[f"m{i}" for i in range(12)], times=np.arange(240) / 120.0),
        SimulationOptions(seed=0),
    )
    centroid = xyz.reshape(-1, 3).mean(axis=0)
    scale = np.linalg.norm(xyz.reshape(-1, 3) - centroid, axis=1).max()
    np.testing.assert_allclose(rig.centroid, centroid)
    np.testing.assert_array_equal(rig.up, [0, 0, 1])
    assert rig.scale == pytest.approx(scale)
    assert 2.0 * scale <= rig.distance <= 3.0 * scale
    azimuths = []
    for video in capture.cameras.videos:
        centres = np.array([f.center for f in video.frames])
        assert np.abs(centres - centres[0]).max() < 1e-9  # static
        offset = centres[0] - centroid
        assert np.linalg.norm(offset) == pytest.approx(rig.distance)
        assert abs(offset[2]) < 1e-6  # at the centroid's height
        f = video.frames[0]
        np.testing.assert_allclose(f.K, [[1000, 0, 499.5], [0, 1000, 499.5], [0, 0, 1]])
        assert project(centroid, f.K, f.R, f.t)[0] == pytest.approx([499.5, 499.5])  # looking at it
        assert f.R[1] @ [0, 0, 1] < 0  # image y points down
        azimuths.append(np.arctan2(offset[1], offset[0]))
    gaps = np.diff(np.sort(np.mod(azimuths, 2 * np.pi)))
    np.testing.assert_allclose(gaps, np.pi / 2, atol=1e-9)  # evenly spread


def test_wide_motion_pushes_cameras_back_until_everything_is_visible() -> None:
    xyz = walking_body(frames=600)  # walks 4 m: far wider than tall
    capture = simulate_capture(xyz, 120.0, SimulationOptions(seed=5, noise_px=0.0))
    projected, _ = reprojection(capture)
    # Every sample, seen by every camera (not only the one it was assigned to), lies inside the image.
    for video in capture.cameras.videos:
        f = video.frames[0]
        uv, depth = project(xyz.reshape(-1, 3), f.K, f.R, f.t)
        assert depth.min() > 0 and uv.min() >= 0 and uv.max() <= 999
    assert projected.min() >= 0


def test_fixed_camera_distance_follows_the_papers_protocol() -> None:
    xyz = walking_body(frames=600)
    capture = simulate_capture(xyz, 120.0, SimulationOptions(seed=5, camera_distance_mm=2700.0))
    centroid = xyz.reshape(-1, 3).mean(axis=0)
    for video in capture.cameras.videos:
        f = video.frames[0]
        assert np.linalg.norm(-f.R.T @ f.t - centroid) == pytest.approx(2700.0)
    with pytest.raises(DynreconError, match="larger distance"):
        simulate_capture(xyz, 120.0, SimulationOptions(camera_distance_mm=300.0))


def test_fixed_distance_grows_the_virtual_images_to_hold_every_projection() -> None:
    # The walk spans 4 m: at 2.7 m it projects beyond 1000 px, which the paper's edge-free cameras still see.
    xyz = walking_body(frames=600)
    capture = simulate_capture(xyz, 120.0, SimulationOptions(seed=5, noise_px=0.0, camera_distance_mm=2700.0))
    for video in capture.cameras.videos:
        f = video.frames[0]
        assert video.width == video.height > 1000
        assert f.K[0, 2] == f.K[1, 2] == pytest.approx((video.width - 1) / 2)
        uv, depth = project(xyz.reshape(-1, 3), f.K, f.R, f.t)
        assert depth.min() > 0 and uv.min() >= 0 and uv.max() <= video.width - 1
    # A motion that fits keeps the option's 1000 px.
    small = walking_body(frames=60)
    compact = simulate_capture(small, 120.0, SimulationOptions(seed=5, camera_distance_mm=9000.0))
    assert {v.width for v in compact.cameras.videos} == {1000}


def test_unconstrained_allows_repeats() -> None:
    rng = np.random.default_rng(0)
    constrained = assign_cameras(5000, 4, False, rng)
    free = assign_cameras(5000, 4, True, rng)
    assert not np.any(constrained[1:] == constrained[:-1])
    repeats = np.mean(free[1:] == free[:-1])
    assert 0.2 < repeats < 0.3  # 1/4 for independent uniform draws
    capture = simulate_capture(walking_body(), 120.0, SimulationOptions(unconstrained=True))
    video_of, _ = captures_by_time(capture)
    assert np.any(video_of[1:] == video_of[:-1])


def test_noise_std_and_miss_fraction() -> None:
    xyz = walking_body(frames=600, markers=20)
    clean = simulate_capture(xyz, 120.0, SimulationOptions(seed=7))
    noisy = simulate_capture(xyz, 120.0, SimulationOptions(seed=7, noise_px=2.0))
    projected, tracked = reprojection(noisy)
    error = tracked - projected
    assert error.std() == pytest.approx(2.0, rel=0.03)
    assert abs(error.mean()) < 0.05
    # Same seed, same cameras and assignment: noise is the only difference.
    assert clean.truth.videos == noisy.truth.videos
    missing = simulate_capture(xyz, 120.0, SimulationOptions(seed=7, miss=0.3))
    assert len(missing.tracks) == round(0.7 * 600 * 20)
    assert (~missing.truth.observed).mean() == pytest.approx(0.3, abs=1e-3)
    projected, tracked = reprojection(missing)
    np.testing.assert_allclose(tracked, projected, atol=1e-9)  # the rows left are exact


def test_step_and_window() -> None:
    xyz = walking_body(frames=300)
    capture = simulate_capture(xyz, 120.0, SimulationOptions(step=4, start=20, length=200))
    _, times = captures_by_time(capture)
    np.testing.assert_allclose(times, np.arange(0, 200, 4) / 120.0)  # 30 Hz overall, from the first capture
    order = np.argsort(capture.truth.extra["time"][:, 0], kind="stable")
    np.testing.assert_array_equal(capture.truth.xyz[order], xyz[20:220:4])


def test_missing_mocap_samples_are_cleaned() -> None:
    xyz = walking_body(frames=100)
    xyz[:, 0] = np.nan  # marker never known: dropped
    xyz[10, 3] = np.nan  # one gap: frame dropped
    capture = simulate_capture(xyz, 120.0, SimulationOptions(), marker_names=[f"m{i}" for i in range(12)])
    assert capture.truth.point_names == [f"m{i}" for i in range(1, 12)]
    assert capture.truth.num_frames == 99
    assert np.isfinite(capture.truth.xyz).all()
    assert 10 / 120 not in set(np.round(capture.truth.extra["time"][:, 0], 9))


@pytest.mark.parametrize(
    "options",
    [
        SimulationOptions(cameras=1),
        SimulationOptions(miss=1.0),
        SimulationOptions(noise_px=-1),
        SimulationOptions(step=0),
    ],
)
def test_bad_options(options: SimulationOptions) -> None:
    with pytest.raises(DynreconError, match="invalid simulation options"):
        simulate_capture(walking_body(frames=20), 120.0, options)


def test_run_writes_readable_files(tmp_path: Path) -> None:
    xyz = walking_body(frames=120)
    mocap = Mocap(xyz=xyz, rate=120.0, marker_names=[f"m{i}" for i in range(12)], times=np.arange(120) / 120.0)
    source = write_trc(tmp_path / "walk.trc", mocap, units="m")
    out = run(source, tmp_path / "sim", SimulationOptions(noise_px=1.0, miss=0.1, seed=2))
    cameras = read_cameras(out / "cameras.json")
    tracks = read_tracks(out / "tracks.csv")
    truth = read_points(out / "truth.csv")
    assert [v.name for v in cameras.videos] == ["cam0", "cam1", "cam2", "cam3"]
    assert cameras.num_frames == truth.num_frames == 120
    assert len(tracks) == round(0.9 * 120 * 12) == truth.observed.sum()
    assert set(tracks.point) == set(truth.point_names) == set(mocap.marker_names)
    order = np.argsort(truth.extra["time"][:, 0], kind="stable")
    np.testing.assert_allclose(truth.xyz[order], xyz, atol=1e-6)  # mm, through metres in the TRC
    # Every track row is an observed truth row of a posed frame.
    index = truth.index()
    names = {n: i for i, n in enumerate(truth.point_names)}
    for row in range(len(tracks)):
        assert truth.observed[index[(tracks.video[row], int(tracks.frame[row]))], names[tracks.point[row]]]
    record = json.loads((out / "simulation.json").read_text())
    assert record["captures"] == 120 and record["camera_distance_mm"] > 0
    with pytest.raises(InputError, match="unknown motion-capture format"):
        run(tmp_path / "walk.bvh", tmp_path / "bad")


def test_a_one_frame_file_is_refused_where_the_cause_is_known(tmp_path: Path) -> None:
    """A static trial of one frame (a calibration pose) simulated into one camera's one frame: `solve` later said
    its video advice; `simulate` says it, naming the file."""
    xyz = walking_body(frames=1)
    mocap = Mocap(xyz=xyz, rate=50.0, marker_names=[f"m{i}" for i in range(12)], times=np.zeros(1))
    source = write_trc(tmp_path / "pose.trc", mocap)
    with pytest.raises(InputError, match=r"pose.trc: 1 capture to simulate .* at least two cameras"):
        run(source, tmp_path / "sim")
    assert not (tmp_path / "sim").exists()


def test_hdm05_protocol(shared_dir: Path) -> None:
    capture, rig = simulate_mocap(
        read_mocap(shared_dir / "data/mocap/hdm05/HDM_dg_06-03_03_120.c3d"), SimulationOptions()
    )
    assert capture.truth.xyz.shape == (202, 44, 3)
    assert 2 * rig.scale <= rig.distance <= 2.5 * rig.scale
    projected, tracked = reprojection(capture)
    np.testing.assert_allclose(tracked, projected, atol=1e-8)
    assert tracked.min() >= 0 and tracked.max() <= 999


def test_cli_mode_paper_is_the_default(tmp_path: Path) -> None:
    from dynrecon.cli import main

    xyz = walking_body(frames=60)
    mocap = Mocap(xyz=xyz, rate=120.0, marker_names=[f"m{i}" for i in range(12)], times=np.arange(60) / 120.0)
    source = write_trc(tmp_path / "walk.trc", mocap)
    common = [str(source), "--noise", "1", "--seed", "3", "--step", "2"]
    assert main(["simulate", *common, "--out", str(tmp_path / "default")]) == 0
    assert main(["simulate", *common, "--mode", "paper", "--out", str(tmp_path / "paper")]) == 0
    for name in ("cameras.json", "tracks.csv", "truth.csv"):
        assert (tmp_path / "default" / name).read_bytes() == (tmp_path / "paper" / name).read_bytes()
    assert not (tmp_path / "paper" / "clocks_truth.json").exists()
    assert read_cameras(tmp_path / "paper" / "cameras.json").videos[0].fps is None


def test_max_missing_keeps_markers_with_gaps(tmp_path: Path) -> None:
    """`--max-missing` (paper and phones): markers missing in more of the frames are left out; a file whose markers
    have gaps keeps them at a looser bound, the frames with a gap then dropped."""
    from dynrecon.cli import main

    xyz = walking_body(frames=60)
    xyz[:12, 5] = np.nan  # 20 % of the frames
    mocap = Mocap(xyz=xyz, rate=120.0, marker_names=[f"m{i}" for i in range(12)], times=np.arange(60) / 120.0)
    source = write_trc(tmp_path / "walk.trc", mocap)
    assert main(["simulate", str(source), "--out", str(tmp_path / "strict")]) == 0
    assert main(["simulate", str(source), "--max-missing", "0.25", "--out", str(tmp_path / "loose")]) == 0
    assert "m5" not in json.loads((tmp_path / "strict" / "simulation.json").read_text())["points"]
    loose = json.loads((tmp_path / "loose" / "simulation.json").read_text())
    assert "m5" in loose["points"] and loose["captures"] == 48 and loose["options"]["max_marker_missing"] == 0.25
    assert main(["simulate", str(source), "--max-missing", "2", "--out", str(tmp_path / "bad")]) == 2


def test_a_new_simulation_removes_an_earlier_solve(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from simulation.simulate import SOLVE_OUTPUTS, clear_solve_outputs

    for name in (*SOLVE_OUTPUTS, "cameras.json"):
        (tmp_path / name).write_text("x")
    clear_solve_outputs(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["cameras.json"]
    assert "removed points3d.csv, sequencing.json, report.json, recording.rrd of an earlier solve" in caplog.text
