from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import DynreconError
from reconstruct.outputs.mocap import Mocap, read_mocap, write_trc
from reconstruct.outputs.points import read_points
from sfm.cameras import FrameCamera, read_cameras
from simulation.phones import (
    PhoneCaptureOptions,
    SimulatedCapture,
    Timestamps,
    run,
    simulate_phones,
    smooth_walk,
)
from simulation.simulate import project
from tracking.tracks import read_tracks

RATE = 120.0


def body(times: np.ndarray, markers: int = 10, seed: int = 1) -> np.ndarray:
    """A smooth Z-up 'body' (1.7 m tall) swinging while it walks along x, at any times (N,) -> (N, M, 3) mm."""
    rng = np.random.default_rng(seed)
    base = np.stack(
        [rng.uniform(-250, 250, markers), rng.uniform(-150, 150, markers), rng.uniform(0, 1700, markers)], axis=1
    )
    phase = rng.uniform(0, 6, markers)[:, None]
    amplitude = rng.uniform(50, 200, (markers, 3))
    swing = amplitude * np.sin(2 * np.pi * 1.2 * times[:, None, None] + phase)
    walk = np.stack([600 * times, np.zeros_like(times), np.zeros_like(times)], axis=1)
    return base[None] + swing + walk[:, None]


def mocap(frames: int = 240) -> Mocap:
    times = np.arange(frames) / RATE
    return Mocap(xyz=body(times), rate=RATE, marker_names=[f"m{i}" for i in range(10)], times=times)


def by_key(capture: SimulatedCapture) -> dict[tuple[str, int], FrameCamera]:
    return {(v.name, f.frame): f for v in capture.cameras.videos for f in v.frames}


def reprojection(capture: SimulatedCapture) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projection of the truth of every track row (N, 2), the track pixels (N, 2), and its false flag (N,)."""
    cams = by_key(capture)
    index = capture.truth.index()
    names = {n: i for i, n in enumerate(capture.truth.point_names)}
    projected = np.empty((len(capture.tracks), 2))
    false = np.empty(len(capture.tracks), dtype=bool)
    for row in range(len(capture.tracks)):
        key = (capture.tracks.video[row], int(capture.tracks.frame[row]))
        cam = cams[key]
        i, p = index[key], names[capture.tracks.point[row]]
        projected[row] = project(capture.truth.xyz[i, p], cam.K, cam.R, cam.t)[0]
        false[row] = capture.truth.extra["false_detection"][i, p] == 1
    return projected, capture.tracks.xy, false


def true_times(capture: SimulatedCapture, clocks: dict[str, tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Capture times from the clock model (offset, rate) and the cameras.json times, and truth.csv's, (F,) each."""
    cams = by_key(capture)
    keys = list(zip(capture.truth.videos, capture.truth.frames.tolist(), strict=True))
    own = np.array([cams[key].time for key in keys], dtype=float)
    offset, rate = np.array([clocks[video] for video, _ in keys]).T
    return offset + rate * own, capture.truth.extra["time"][:, 0]


def test_clock_model_round_trip_through_the_files(tmp_path: Path) -> None:
    source = write_trc(tmp_path / "walk.trc", mocap(), units="mm")
    options = PhoneCaptureOptions(fps=(30.0, 29.97, 25.0, 59.94), offset_s=(-0.3, 0.4), drift_ppm=300.0, seed=4)
    out = run(source, tmp_path / "sim", options)
    clocks = json.loads((out / "clocks_truth.json").read_text())
    cameras = read_cameras(out / "cameras.json")
    truth = read_points(out / "truth.csv")
    assert len(read_tracks(out / "tracks.csv")) == truth.observed.sum() == truth.xyz.shape[0] * 10
    assert clocks["timestamps"] == "cfr" and clocks["jitter_ms"] == 0
    index = truth.index()
    for entry, video, fps in zip(clocks["videos"], cameras.videos, options.fps or (), strict=True):
        assert entry["name"] == video.name and entry["fps"] == video.fps == fps
        assert -0.3 <= entry["offset_s"] <= 0.4
        assert entry["rate"] == pytest.approx(1 + entry["drift"], abs=1e-15)
        assert 1e-7 < abs(entry["drift"]) <= 300e-6 and entry["drift_ppm"] == pytest.approx(entry["drift"] * 1e6)
        frames = video.frame_numbers()
        assert entry["frames"] == len(frames) > 10
        # Consecutive frames (the mocap has no gap); the first one is the first inside the window.
        np.testing.assert_array_equal(frames, np.arange(frames[0], frames[0] + len(frames)))
        own = np.array([f.time for f in video.frames])
        np.testing.assert_allclose(own, frames / fps, atol=1e-12)  # CFR: the decoder reports k / fps
        model = entry["offset_s"] + entry["rate"] * own
        recorded = truth.extra["time"][[index[(video.name, int(k))] for k in frames], 0]
        np.testing.assert_allclose(recorded, model, atol=1e-9)
        # The first frame is frame 0 or the first inside the window; the video runs to the window's end.
        assert model[0] >= 0 and (frames[0] == 0 or model[0] - entry["rate"] / fps < 0)
        assert (frames[0] == 0) == (entry["offset_s"] >= 0)
        assert model[-1] <= 239 / RATE < model[-1] + entry["rate"] / fps
    # The offsets differ, so frames of different cameras do not line up with the mocap samples or each other.
    assert len({round(e["offset_s"], 6) for e in clocks["videos"]}) == 4


def test_truth_is_the_mocap_interpolated_at_each_capture_time() -> None:
    motion = mocap()
    # Zero offsets at 30 and 24 fps: frame k is mocap sample 4k (30 fps) or 5k (24 fps), where the spline is exact.
    capture, _ = simulate_phones(motion, PhoneCaptureOptions(cameras=2, fps=(30.0, 24.0), offset_s=(0.0, 0.0)))
    truth = capture.truth
    for v, step in (("cam0", 4), ("cam1", 5)):
        rows = [i for i, name in enumerate(truth.videos) if name == v]
        samples = truth.frames[rows] * step
        np.testing.assert_allclose(truth.xyz[rows], motion.xyz[samples], atol=1e-6)
    # Anywhere else, the cubic spline of a 120 Hz smooth motion is within a few hundredths of a mm.
    other, _ = simulate_phones(motion, PhoneCaptureOptions(drift_ppm=200.0, jitter_ms=2.0, seed=3))
    times = other.truth.extra["time"][:, 0]
    off_sample = np.abs(times * RATE - np.round(times * RATE)) > 0.1
    assert off_sample.mean() > 0.6  # 0.8 expected for random phases
    np.testing.assert_allclose(other.truth.xyz, body(times), atol=0.05)


def test_captures_are_concurrent_and_rates_are_free() -> None:
    capture, record = simulate_phones(
        mocap(), PhoneCaptureOptions(cameras=3, fps=(30.0, 30.0, 59.94), offset_s=(0.0, 0.0))
    )
    truth = capture.truth
    times = {v: truth.extra["time"][[i for i, n in enumerate(truth.videos) if n == v], 0] for v in record.frames}
    np.testing.assert_allclose(times["cam0"], times["cam1"])  # the same instants, both captured
    assert np.diff(times["cam2"]).mean() == pytest.approx(1 / 59.94)
    assert record.frames == {"cam0": 60, "cam1": 60, "cam2": 120}  # 2 s window, 239/120 s long


def test_jitter_cfr_hides_it_vfr_shows_it() -> None:
    options = PhoneCaptureOptions(fps=(30.0, 25.0, 24.0, 29.97), jitter_ms=3.0, drift_ppm=100.0, seed=5)
    for timestamps in Timestamps:
        options.timestamps = timestamps
        capture, record = simulate_phones(mocap(480), options)
        clocks = {c.name: (c.offset_s, c.rate) for c in record.clocks}
        model, recorded = true_times(capture, clocks)
        if timestamps is Timestamps.CFR:
            residual = recorded - model
            assert residual.std() == pytest.approx(3e-3, rel=0.15) and abs(residual.mean()) < 5e-4
            assert np.abs(residual).max() <= 0.4 / 24.0 + 1e-12
        else:
            np.testing.assert_allclose(recorded, model, atol=1e-9)
        for video in capture.cameras.videos:  # captures keep their order
            assert np.all(np.diff([f.time for f in video.frames]) > 0)


def test_noise_free_tracks_are_the_projections_by_each_frames_camera() -> None:
    capture, record = simulate_phones(mocap(), PhoneCaptureOptions(handheld=True, jitter_ms=2.0, seed=2))
    projected, tracked, false = reprojection(capture)
    assert not false.any() and len(tracked) == capture.truth.observed.sum() > 0
    np.testing.assert_allclose(tracked, projected, atol=1e-9)
    assert tracked.min() >= -0.5 and tracked.max() <= 999.5
    assert record.out_of_image == (~capture.truth.observed).sum()


def test_handheld_cameras_move_smoothly_and_see_the_points() -> None:
    motion = mocap(480)
    capture, record = simulate_phones(
        motion, PhoneCaptureOptions(handheld=True, shake_mm=20.0, shake_deg=1.0, fps=(59.94, 30.0, 25.0, 24.0), seed=6)
    )
    static, _ = simulate_phones(motion, PhoneCaptureOptions(fps=(59.94, 30.0, 25.0, 24.0), seed=6))
    rig = record.rig
    assert rig is not None
    index = capture.truth.index()
    for video, still in zip(capture.cameras.videos, static.cameras.videos, strict=True):
        centres = np.array([f.center for f in video.frames])
        still_centres = np.array([f.center for f in still.frames])
        assert np.abs(still_centres - still_centres[0]).max() < 1e-9
        excursion = centres - still_centres[0]  # the same seed places the same base camera
        assert 3.0 < excursion.std() < 40.0  # about shake_mm over a 4 s window
        # Smooth, not per-frame noise: second differences are far smaller than first differences.
        first, second = np.diff(centres, axis=0), np.diff(centres, 2, axis=0)
        assert np.abs(first).max() < 10.0 and np.sqrt((second**2).mean() / (first**2).mean()) < 0.3
        R = np.array([f.R for f in video.frames])
        step = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1)))
        assert step.max() < 0.3
        turn = np.degrees(np.arccos(np.clip((np.einsum("nij,ij->n", R, still.frames[0].R) - 1) / 2, -1, 1)))
        assert 0.2 < turn.mean() < 5.0
        # The points stay in front and almost all inside the image.
        for frame in video.frames:
            _, depth = project(capture.truth.xyz[index[(video.name, frame.frame)]], frame.K, frame.R, frame.t)
            assert depth.min() > 0.5 * rig.distance
    assert capture.truth.observed.mean() > 0.95


def test_smooth_walk_is_stationary_with_the_requested_spread() -> None:
    rng = np.random.default_rng(0)
    walk = smooth_walk(np.linspace(0, 200, 20001), 3, 2.0, 1.0, rng)
    assert walk.std(axis=0) == pytest.approx([2.0, 2.0, 2.0], rel=0.2)
    step = np.diff(walk, axis=0)
    assert step.std(axis=0) == pytest.approx([0.02, 0.02, 0.02], rel=0.2)  # velocity std = 2 / 1 s, 10 ms steps
    assert np.abs(step).max() < 0.1


def test_noise_miss_and_false_detections() -> None:
    options = PhoneCaptureOptions(noise_px=1.5, miss=0.1, false_fraction=0.05, false_min_px=80.0, seed=8)
    capture, record = simulate_phones(mocap(), options)
    truth = capture.truth
    visible = truth.observed.size - record.out_of_image
    assert len(capture.tracks) == visible - round(0.1 * visible) == truth.observed.sum()
    projected, tracked, false = reprojection(capture)
    assert false.sum() == round(0.05 * len(capture.tracks)) == record.false_detections
    error = tracked - projected
    assert np.linalg.norm(error[false], axis=1).min() >= 80.0
    assert error[~false].std() == pytest.approx(1.5, rel=0.05)
    assert tracked.min() >= -0.5 - 6 and tracked.max() <= 999.5 + 6  # noise may cross the border a little
    assert (truth.extra["false_detection"][~truth.observed] == 0).all()


def test_mocap_gaps_and_window_edges_drop_captures() -> None:
    motion = mocap()
    motion.xyz[100:106, 2] = np.nan  # a 50 ms hole: every camera has a capture in it
    capture, record = simulate_phones(motion, PhoneCaptureOptions(seed=1, start=10, length=200))
    times = capture.truth.extra["time"][:, 0]
    assert not ((times > 89.5 / RATE) & (times < 95.5 / RATE)).any()  # window frame 90 = file frame 100
    assert times.min() >= 0 and times.max() <= 199 / RATE
    assert sum(record.dropped.values()) >= 4
    for video in capture.cameras.videos:  # dropped frames are absent, the others keep their numbers
        frames = video.frame_numbers()
        assert len(frames) == record.frames[video.name] and np.all(np.diff(frames) >= 1)
    np.testing.assert_allclose(capture.truth.xyz, body(times + 10 / RATE)[:, capture_points(capture)], atol=0.05)


def capture_points(capture: SimulatedCapture) -> list[int]:
    return [int(name[1:]) for name in capture.truth.point_names]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (PhoneCaptureOptions(cameras=1), "at least 2"),
        (PhoneCaptureOptions(fps=(30.0, 25.0)), "give one per camera"),
        (PhoneCaptureOptions(cameras=2, fps=(30.0, 0.0)), "within 1..1000"),
        (PhoneCaptureOptions(offset_s=(1.0, 0.0)), "min <= max"),
        (PhoneCaptureOptions(jitter_ms=-1.0), "jitter"),
        (PhoneCaptureOptions(false_fraction=1.0), "false fraction"),
        (PhoneCaptureOptions(miss=1.0), "miss"),
    ],
)
def test_bad_options(options: PhoneCaptureOptions, message: str) -> None:
    with pytest.raises(DynreconError, match=message):
        simulate_phones(mocap(40), options)


def test_impossible_captures_are_errors() -> None:
    with pytest.raises(DynreconError, match="no camera captured"):
        simulate_phones(mocap(40), PhoneCaptureOptions(offset_s=(5.0, 6.0)))
    with pytest.raises(DynreconError, match="larger camera distance"):
        simulate_phones(mocap(240), PhoneCaptureOptions(handheld=True, shake_mm=3000.0, seed=1))


def test_cli_phones(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    source = write_trc(tmp_path / "walk.trc", mocap(), units="m")
    out = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                str(source),
                "--out",
                str(out),
                "--mode",
                "phones",
                "--cameras",
                "3",
                "--fps",
                "30,25,59.94",
                "--offsets",
                "0,0.2",
                "--drift-ppm",
                "100",
                "--jitter-ms",
                "1",
                "--vfr",
                "--handheld",
                "--shake-mm",
                "10",
                "--shake-deg",
                "0.5",
                "--noise",
                "1",
                "--miss",
                "0.1",
                "--false",
                "0.02",
                "--seed",
                "3",
                "--length",
                "200",
            ]
        )
        == 0
    )
    assert "in 3 cameras" in capsys.readouterr().out
    clocks = json.loads((out / "clocks_truth.json").read_text())
    simulation = json.loads((out / "simulation.json").read_text())
    assert [c["fps"] for c in clocks["videos"]] == [30.0, 25.0, 59.94] and clocks["timestamps"] == "vfr"
    assert all(0 <= c["offset_s"] <= 0.2 and abs(c["drift_ppm"]) <= 100 for c in clocks["videos"])
    assert simulation["mode"] == "phones" and simulation["options"]["handheld"] is True
    truth = read_points(out / "truth.csv")
    tracks = read_tracks(out / "tracks.csv")
    assert len(tracks) == truth.observed.sum() and truth.extra["false_detection"].sum() == round(0.02 * len(tracks))
    assert truth.extra["time"].max() <= 199 / RATE
    cameras = read_cameras(out / "cameras.json")
    assert [v.fps for v in cameras.videos] == [30.0, 25.0, 59.94]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--mode", "phones"], "needs a MOCAP file"),
        (["MOCAP", "--mode", "phones", "--step", "2"], "--step does not apply to --mode phones"),
        (["MOCAP", "--mode", "phones", "--unconstrained"], "--unconstrained does not apply"),
        (["MOCAP", "--jitter-ms", "2"], "--jitter-ms does not apply to --mode paper"),
        (["MOCAP", "--mode", "phones", "--fps", "30,x,25,24"], "comma-separated numbers"),
        (["MOCAP", "--mode", "phones", "--fps", "30,25"], "give one per camera"),
        (["MOCAP", "--mode", "phones", "--offsets", "0.5"], "--offsets '0.5'"),
        (["MOCAP", "--mode", "phones", "--duration", "3"], "--duration does not apply"),
        (["MOCAP", "--mode", "phones", "--false", "1.5"], "false fraction"),
    ],
)
def test_cli_bad_options_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    source = write_trc(tmp_path / "walk.trc", mocap(40), units="m")
    argv = [str(source) if a == "MOCAP" else a for a in argv]
    assert main(["simulate", *argv, "--out", str(tmp_path / "x")]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_hdm05_phones(shared_dir: Path) -> None:
    motion = read_mocap(shared_dir / "data/mocap/hdm05/HDM_dg_06-03_03_120.c3d")
    capture, record = simulate_phones(motion, PhoneCaptureOptions(handheld=True, jitter_ms=1.0))
    assert capture.truth.xyz.shape[1] == 44 and sum(record.frames.values()) == capture.truth.num_frames > 150
    projected, tracked, _ = reprojection(capture)
    np.testing.assert_allclose(tracked, projected, atol=1e-8)


def test_true_clocks_are_the_solvers_clock_model() -> None:
    """Each simulated camera's true clock is an affine `reconstruct.clocks.model.Clock`: its report form gives the
    drawn offset and rate, and its inverse maps capture times back to own times."""
    _, record = simulate_phones(mocap(240), PhoneCaptureOptions(cameras=3, drift_ppm=200.0, seed=2))
    for true_clock in record.clocks:
        values, _ = true_clock.clock.offset_rate_drift()
        assert values.tolist() == [true_clock.offset_s, true_clock.rate, 0.0]
        own = np.arange(10) / true_clock.fps
        np.testing.assert_allclose(true_clock.own_time(true_clock.global_time(own)), own, atol=1e-12)
