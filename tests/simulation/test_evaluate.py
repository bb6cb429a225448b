from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest

import dynrecon.cli
from dynrecon.errors import InputError
from reconstruct.outputs.mocap import Mocap, write_trc
from reconstruct.outputs.points import FramePoints, read_points, write_points
from sfm.cameras import read_cameras
from simulation.cli import add_commands
from simulation.evaluate import evaluate, run
from tracking.tracks import read_tracks

Pair = tuple[FramePoints, FramePoints]


def frame_points(errors: list[list[float]], *, observed: list[list[bool]] | None = None) -> Pair:
    """(estimate, truth) with the given error per (frame, point), each along a random direction."""
    rng = np.random.default_rng(0)
    err = np.array(errors, dtype=float)
    F, P = err.shape
    truth_xyz = rng.uniform(-1000, 1000, (F, P, 3))
    direction = rng.normal(size=(F, P, 3))
    direction /= np.linalg.norm(direction, axis=2, keepdims=True)
    estimate_xyz = truth_xyz + np.nan_to_num(err)[..., None] * direction
    estimate_xyz[np.isnan(err)] = np.nan
    obs = np.array(observed, dtype=bool) if observed is not None else np.ones((F, P), dtype=bool)
    videos = ["a", "b"] * (F // 2) + ["a"] * (F % 2)
    frames = np.arange(F) // 2
    names = [f"p{i}" for i in range(P)]
    truth = FramePoints(
        videos=list(videos),
        frames=frames,
        point_names=names,
        xyz=truth_xyz,
        observed=obs,
        extra={"time": np.repeat(np.arange(F)[:, None] / 120.0, P, axis=1)},
    )
    estimate = FramePoints(
        videos=list(videos), frames=frames.copy(), point_names=list(names), xyz=estimate_xyz, observed=obs.copy()
    )
    return estimate, truth


def test_hand_made_errors() -> None:
    estimate, truth = frame_points(
        [[1.0, 9.99, 10.0], [15.0, 45.0, 99.0], [150.0, math.nan, 0.0], [5.0, 5.0, 5.0]],
        observed=[[1, 1, 1], [1, 0, 1], [1, 0, 1], [1, 1, 1]],
    )
    accuracy = evaluate(estimate, truth)
    assert accuracy.count == 12 and accuracy.unreconstructed == 1 and accuracy.no_truth == 0
    # Under 10: 1, 9.99, 0, 5, 5, 5 -> 6 of 12 (10.0 is not under 10); the NaN fails everywhere.
    np.testing.assert_allclose(accuracy.share_under, np.array([6, 8, 8, 8, 9, 10]) / 12)
    np.testing.assert_allclose(accuracy.share_under_unobserved, [0, 0, 0, 0, 0.5, 0.5])
    np.testing.assert_allclose(accuracy.share_under_observed, np.array([6, 8, 8, 8, 8, 9]) / 10)
    finite = [1, 9.99, 10, 15, 45, 99, 150, 0, 5, 5, 5]
    assert accuracy.mean == pytest.approx(np.mean(finite))
    assert accuracy.median == pytest.approx(np.median([*finite, np.inf]))
    assert "<10:  50.00%" in accuracy.table() and "unreconstructed 1/12" in accuracy.table()
    assert "\n" not in accuracy.table()


def test_rows_are_matched_by_key_not_position() -> None:
    estimate, truth = frame_points([[1.0, 2.0], [3.0, 400.0], [5.0, 6.0]])
    shuffled = FramePoints(
        videos=estimate.videos[::-1],
        frames=estimate.frames[::-1],
        point_names=estimate.point_names[::-1],
        xyz=estimate.xyz[::-1, ::-1],
        observed=estimate.observed[::-1, ::-1],
    )
    a, b = evaluate(estimate, truth), evaluate(shuffled, truth)
    np.testing.assert_allclose(np.sort(a.errors), np.sort(b.errors))
    np.testing.assert_allclose(np.sort(a.errors), [1, 2, 3, 5, 6, 400])


def test_nan_truth_is_not_scored() -> None:
    estimate, truth = frame_points([[1.0, 2.0], [3.0, 4.0]])
    truth.xyz[0, 1] = np.nan
    accuracy = evaluate(estimate, truth)
    assert accuracy.count == 3 and accuracy.no_truth == 1
    assert accuracy.share_under[0] == 1.0


def test_mismatched_rows_are_errors() -> None:
    estimate, truth = frame_points([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    fewer = FramePoints(
        videos=estimate.videos[:2],
        frames=estimate.frames[:2],
        point_names=estimate.point_names,
        xyz=estimate.xyz[:2],
        observed=estimate.observed[:2],
    )
    with pytest.raises(InputError, match="video 'a' frame 1 of the truth has no row"):
        evaluate(fewer, truth)
    with pytest.raises(InputError, match="video 'a' frame 1 is not in the truth"):
        evaluate(
            estimate,
            FramePoints(
                videos=truth.videos[:2],
                frames=truth.frames[:2],
                point_names=truth.point_names,
                xyz=truth.xyz[:2],
                observed=truth.observed[:2],
            ),
        )
    renamed = FramePoints(
        videos=estimate.videos,
        frames=estimate.frames,
        point_names=["p0", "q"],
        xyz=estimate.xyz,
        observed=estimate.observed,
    )
    with pytest.raises(InputError, match="point 'q' is not in the truth"):
        evaluate(renamed, truth)
    one_point = FramePoints(
        videos=estimate.videos,
        frames=estimate.frames,
        point_names=["p0"],
        xyz=estimate.xyz[:, :1],
        observed=estimate.observed[:, :1],
    )
    with pytest.raises(InputError, match="point 'p1' of the truth has no rows"):
        evaluate(one_point, truth)


def test_a_video_left_out_of_the_solve_counts_as_unreconstructed(caplog: pytest.LogCaptureFixture) -> None:
    """A solve that left a video out (its clock not found: report.json temporal.left_out) writes no row for it: its
    truth rows are scored as unreconstructed, not refused and not dropped from the count."""
    _, truth = frame_points([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    two = FramePoints(
        videos=["a", "a", "b"],
        frames=np.array([0, 1, 0]),
        point_names=truth.point_names,
        xyz=truth.xyz,
        observed=truth.observed,
    )
    without_b = FramePoints(
        videos=["a", "a"],
        frames=np.array([0, 1]),
        point_names=truth.point_names,
        xyz=truth.xyz[:2] + 0.5,
        observed=truth.observed[:2],
    )
    with caplog.at_level(logging.WARNING):
        accuracy = evaluate(without_b, two)
    assert accuracy.count == 6 and accuracy.unreconstructed == 2
    assert any("video(s) b have no rows" in r.getMessage() for r in caplog.records)


def test_run_reads_files_and_reports_missing_ones(tmp_path: Path) -> None:
    estimate, truth = frame_points([[1.0, 25.0], [3.0, math.nan]])
    write_points(tmp_path / "points3d.csv", estimate)
    write_points(tmp_path / "truth.csv", truth)
    accuracy = run(tmp_path)
    np.testing.assert_allclose(accuracy.share_under, [0.5, 0.5, 0.75, 0.75, 0.75, 0.75])
    assert accuracy.unreconstructed == 1
    other = tmp_path / "other"
    other.mkdir()
    write_points(other / "points3d.csv", estimate)
    assert run(other, tmp_path / "truth.csv").count == 4
    with pytest.raises(InputError, match=r"truth\.csv: file not found"):
        run(other)
    with pytest.raises(InputError, match=r"points3d\.csv: file not found"):
        run(tmp_path / "nowhere")


# ------------------------------------------------------------------------------------------------------------
# CLI


def cli(argv: list[str], monkeypatch: pytest.MonkeyPatch) -> int:
    """dynrecon.cli.main, with this module's commands registered if reconstruct.cli does not do it yet."""
    parser = argparse.ArgumentParser()
    probe = parser.add_subparsers()
    for name in dynrecon.cli.COMMAND_MODULES:
        __import__(name, fromlist=["add_commands"]).add_commands(probe)
    if "simulate" not in probe.choices:
        modules = (*dynrecon.cli.COMMAND_MODULES, "simulation.cli")
        monkeypatch.setattr(dynrecon.cli, "COMMAND_MODULES", modules)
    return dynrecon.cli.main(argv)


def _mocap_file(tmp_path: Path) -> Path:
    rng = np.random.default_rng(4)
    t = np.arange(120) / 120.0
    base = np.stack([rng.uniform(-300, 300, 10), rng.uniform(0, 1700, 10), rng.uniform(-200, 200, 10)], axis=1)
    xyz = base[None] + 100 * np.sin(2 * np.pi * t[:, None, None] + rng.uniform(0, 6, (10, 3)))
    mocap = Mocap(xyz=xyz, rate=120.0, marker_names=[f"m{i}" for i in range(10)], times=t)
    return write_trc(tmp_path / "motion.trc", mocap, units="m")


def test_cli_simulate_then_evaluate_truth_against_itself(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    source = _mocap_file(tmp_path)
    out = tmp_path / "sim"
    assert (
        cli(
            [
                "simulate",
                str(source),
                "--out",
                str(out),
                "--cameras",
                "3",
                "--step",
                "2",
                "--noise",
                "0.5",
                "--miss",
                "0.2",
                "--seed",
                "9",
                "--start",
                "10",
                "--length",
                "100",
            ],
            monkeypatch,
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "50 captures of 10 points in 3 cameras" in printed
    cameras = read_cameras(out / "cameras.json")
    distance = json.loads((out / "simulation.json").read_text())["camera_distance_mm"]
    assert f"(1 px ~ {distance / cameras.videos[0].frames[0].K[0, 0]:.2g} mm there)" in printed
    truth = read_points(out / "truth.csv")
    tracks = read_tracks(out / "tracks.csv")
    assert truth.num_frames == 50 and len(tracks) == 400
    assert sorted(set(truth.videos)) == ["cam0", "cam1", "cam2"]
    # The truth scored against itself is perfect; a copy with one point shifted by 15 mm is not.
    write_points(out / "points3d.csv", truth)
    assert cli(["evaluate", str(out)], monkeypatch) == 0
    assert "<10: 100.00%" in capsys.readouterr().out
    truth.xyz[0, 0] += [15.0, 0, 0]
    write_points(tmp_path / "points3d.csv", truth)
    assert cli(["evaluate", str(tmp_path), "--truth", str(out / "truth.csv"), "--json"], monkeypatch) == 0
    numbers = json.loads(capsys.readouterr().out)
    assert numbers["share_under"][:2] == [pytest.approx(499 / 500), 1.0]
    assert numbers["count"] == 500


def test_cli_unconstrained_and_bad_input(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    source = _mocap_file(tmp_path)
    assert cli(["simulate", str(source), "--out", str(tmp_path / "u"), "--unconstrained"], monkeypatch) == 0
    capsys.readouterr()
    bad = tmp_path / "motion.xyz"
    bad.write_text("1 2 3\n")
    assert cli(["simulate", str(bad), "--out", str(tmp_path / "x")], monkeypatch) == 2
    error = capsys.readouterr().err
    assert "unknown motion-capture format" in error and error.count("\n") == 1
    assert cli(["simulate", str(source), "--out", str(tmp_path / "x"), "--cameras", "1"], monkeypatch) == 2
    assert "at least 2" in capsys.readouterr().err
    assert cli(["evaluate", str(tmp_path / "u")], monkeypatch) == 2  # no points3d.csv there
    assert "points3d.csv: file not found" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_add_commands_on_a_local_parser() -> None:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["simulate", "m.c3d", "--out", "o", "--noise", "2", "--miss", "0.3"])
    values = (args.noise, args.miss, args.cameras, args.step, args.unconstrained, args.length)
    assert values == (2.0, 0.3, 4, 1, False, None)
    args = parser.parse_args(["evaluate", "d", "--truth", "t.csv"])
    assert args.truth == Path("t.csv") and callable(args.func)
