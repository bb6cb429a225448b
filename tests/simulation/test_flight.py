from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import DynreconError
from reconstruct.outputs.points import read_points
from sfm.cameras import read_cameras
from simulation.flight import FlightOptions, run, simulate_flight
from simulation.simulate import SimulatedCapture, project
from tracking.tracks import read_tracks


def residuals(capture: SimulatedCapture) -> tuple[np.ndarray, np.ndarray]:
    """Track pixel minus the projection of the truth (N, 2), and the false-detection flag (N,), per track row."""
    cams = {(v.name, f.frame): f for v in capture.cameras.videos for f in v.frames}
    index = capture.truth.index()
    error = np.empty((len(capture.tracks), 2))
    false = np.empty(len(capture.tracks), dtype=bool)
    for row in range(len(capture.tracks)):
        key = (capture.tracks.video[row], int(capture.tracks.frame[row]))
        cam = cams[key]
        error[row] = capture.tracks.xy[row] - project(capture.truth.xyz[index[key], 0], cam.K, cam.R, cam.t)[0]
        false[row] = capture.truth.extra["false_detection"][index[key], 0] == 1
    return error, false


def test_path_and_cameras_as_set() -> None:
    options = FlightOptions(duration_s=6.0, speed_mps=12.0, extent_m=15.0, climb_m=3.0, altitude_m=20.0, seed=2)
    capture, record, scene = simulate_flight(options)
    t = np.linspace(0, 6.0, 3001)
    speed = np.linalg.norm(scene.velocity(t), axis=1) / 1000
    assert speed.mean() == pytest.approx(12.0, rel=1e-3) and speed.max() < 3 * 12.0
    path = scene.position(t)[:, 0]
    assert np.abs(path[:, :2]).max() <= 15000 + 1e-6 and np.abs(path[:, 2] - 20000).max() <= 3000 + 1e-6
    # The velocity is the derivative of the position (mm/s).
    np.testing.assert_allclose(np.gradient(path, t, axis=0)[1:-1], scene.velocity(t)[1:-1], rtol=0, atol=50.0)
    horizontal = np.linalg.norm(scene.camera_centres[:, :2], axis=1)
    assert len(horizontal) == 5 and horizontal.min() >= 30000 and horizontal.max() <= 100000
    np.testing.assert_allclose(scene.camera_centres[:, 2], 1500.0)
    # The truth is the path at each true capture time; one point, in mm.
    assert capture.truth.point_names == ["drone"]
    np.testing.assert_allclose(capture.truth.xyz[:, 0], scene.position(capture.truth.extra["time"][:, 0])[:, 0])
    # Each camera sees the drone almost always; handheld by default.
    assert record.out_of_image < 0.05 * capture.truth.num_frames
    centres = np.array([f.center for f in capture.cameras.videos[0].frames])
    assert 5.0 < np.linalg.norm(centres - centres.mean(axis=0), axis=1).mean() < 200.0


def test_detections_noise_and_false_share() -> None:
    capture, record, _ = simulate_flight(FlightOptions(duration_s=8.0, noise_px=1.5, false_fraction=0.04, seed=3))
    error, false = residuals(capture)
    assert false.sum() == round(0.04 * len(capture.tracks)) == record.false_detections > 20
    assert np.linalg.norm(error[false], axis=1).min() >= 50.0
    assert error[~false].std() == pytest.approx(1.5, rel=0.05)
    # False detections are uniform in the 1920 x 1080 image.
    false_xy = capture.tracks.xy[false]
    assert false_xy.min() >= -0.5 and false_xy[:, 0].max() <= 1919.5 and false_xy[:, 1].max() <= 1079.5
    assert false_xy[:, 0].std() == pytest.approx(1920 / np.sqrt(12), rel=0.25)


def test_noise_free_flight_is_exact_and_clocks_round_trip() -> None:
    options = FlightOptions(
        duration_s=4.0,
        noise_px=0.0,
        false_fraction=0.0,
        handheld=False,
        drift_ppm=500.0,
        fps=(30.0, 25.0, 59.94, 24.0, 29.97),
        seed=4,
    )
    capture, record, _ = simulate_flight(options)
    error, false = residuals(capture)
    assert not false.any()
    np.testing.assert_allclose(error, 0.0, atol=1e-8)
    clocks = {c.name: c for c in record.clocks}
    for video in capture.cameras.videos:
        rows = [i for i, v in enumerate(capture.truth.videos) if v == video.name]
        model = clocks[video.name].global_time(np.array([f.time for f in video.frames]))
        np.testing.assert_allclose(capture.truth.extra["time"][rows, 0], model, atol=1e-9)
        assert video.fps == clocks[video.name].fps and video.width == 1920 and video.height == 1080


def test_bad_flight_options() -> None:
    with pytest.raises(DynreconError, match="invalid flight options"):
        simulate_flight(FlightOptions(duration_s=0.0))
    with pytest.raises(DynreconError, match="camera distance"):
        simulate_flight(FlightOptions(distance_m=(100.0, 30.0)))
    with pytest.raises(DynreconError, match="invalid simulation options"):
        simulate_flight(FlightOptions(noise_px=-1.0))
    with pytest.raises(DynreconError, match="give one per camera"):
        simulate_flight(FlightOptions(fps=(30.0, 25.0)))


def test_run_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = run(tmp_path / "lib", FlightOptions(duration_s=2.0, seed=1))
    simulation = json.loads((out / "simulation.json").read_text())
    assert simulation["mode"] == "flight" and simulation["units"] == "mm"
    assert simulation["path"]["mean_speed_mps"] == pytest.approx(10.0, rel=1e-3)
    cli_out = tmp_path / "cli"
    assert (
        main(
            [
                "simulate",
                "--mode",
                "flight",
                "--out",
                str(cli_out),
                "--duration",
                "2",
                "--speed",
                "8",
                "--distance-m",
                "40,60",
                "--cameras",
                "4",
                "--fps",
                "30,25,24,59.94",
                "--offsets",
                "0,1",
                "--noise",
                "2",
                "--false",
                "0.05",
                "--no-handheld",
                "--seed",
                "5",
            ]
        )
        == 0
    )
    assert "in 4 cameras" in capsys.readouterr().out
    truth = read_points(cli_out / "truth.csv")
    tracks = read_tracks(cli_out / "tracks.csv")
    cameras = read_cameras(cli_out / "cameras.json")
    clocks = json.loads((cli_out / "clocks_truth.json").read_text())
    simulation = json.loads((cli_out / "simulation.json").read_text())
    assert [c["fps"] for c in clocks["videos"]] == [30.0, 25.0, 24.0, 59.94]
    assert all(0 <= c["offset_s"] <= 1 for c in clocks["videos"]) and clocks["time_origin"] == "the start of the flight"
    assert simulation["options"]["handheld"] is False and simulation["path"]["mean_speed_mps"] == pytest.approx(8.0)
    assert truth.num_frames == cameras.num_frames and len(tracks) == truth.observed.sum()
    assert truth.extra["false_detection"].sum() == round(0.05 * len(tracks))
    for video in cameras.videos:
        centres = np.array([f.center for f in video.frames])
        assert np.abs(centres - centres[0]).max() < 1e-6  # --no-handheld
        assert 40000 <= np.linalg.norm(centres[0, :2]) <= 60000


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["MOCAP", "--mode", "flight"], "drop the MOCAP argument"),
        (["--mode", "flight", "--step", "2"], "--step does not apply to --mode flight"),
        (["--mode", "flight", "--start", "2"], "--start does not apply"),
        (["--mode", "flight", "--distance", "2700"], "--distance does not apply"),
        (["--mode", "flight", "--distance-m", "30"], "--distance-m '30'"),
        (["--mode", "flight", "--duration", "-1"], "duration"),
        (["--distance-m", "30,50"], "--distance-m does not apply to --mode paper"),
    ],
)
def test_cli_flight_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    argv = [str(tmp_path / "m.c3d") if a == "MOCAP" else a for a in argv]
    if "--mode" not in argv:
        argv = [str(tmp_path / "m.c3d"), *argv]
    assert main(["simulate", *argv, "--out", str(tmp_path / "x")]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1
    assert not (tmp_path / "x").exists()
