import json

import numpy as np
from rrd_reader import entities, verify
from synthetic_motion import smooth_motion

from dynrecon.cli import main
from reconstruct.outputs.points import read_points, read_sequencing
from sfm.cameras import write_cameras
from simulation.simulate import SimulationOptions, simulate_capture
from tracking.tracks import write_tracks


def _solve(folder, out, *options):
    """`dynrecon solve` on folder's cameras.json and tracks.csv into `out`; its exit code."""
    args = ["--cameras", str(folder / "cameras.json"), "--tracks", str(folder / "tracks.csv"), "--out", str(out)]
    return main(["solve", *args, *options])


def _capture(tmp_path, frames=80, points=4):
    capture = simulate_capture(smooth_motion(frames, points), 120.0, SimulationOptions(seed=3))
    write_cameras(tmp_path / "cameras.json", capture.cameras)
    write_tracks(tmp_path / "tracks.csv", capture.tracks)
    return capture


def test_solve_writes_every_output(tmp_path, capsys):
    # the self-expressive solve's own outputs: with 4 points and times the default takes the tracks path (below)
    capture = _capture(tmp_path)
    out = tmp_path / "out"
    code = main(
        [
            "solve",
            "--cameras",
            str(tmp_path / "cameras.json"),
            "--tracks",
            str(tmp_path / "tracks.csv"),
            "--out",
            str(out),
            "--refinement",
            "none",
        ]
    )
    assert code == 0
    said = capsys.readouterr()
    assert "recording.rrd" in said.out
    assert "solve (smooth)" in said.err  # the seed solve's progress, off a terminal too (minutes on long captures)
    points = read_points(out / "points3d.csv")
    assert points.xyz.shape == (capture.truth.num_frames, 4, 3)
    index = capture.truth.index()
    truth = np.stack([capture.truth.xyz[index[(v, int(f))]] for v, f in zip(points.videos, points.frames, strict=True)])
    assert np.median(np.linalg.norm(points.xyz - truth, axis=-1)) < 1.0
    sequencing = read_sequencing(out / "sequencing.json")
    assert all(abs(w.sum() - 1) < 1e-3 for w in sequencing.weights)
    report = json.loads((out / "report.json").read_text())
    assert report["parameters"]["lambda1"] == 0.05 and report["parameters"]["constraint"] == "soft"
    assert [s["name"] for s in report["stages"]] == ["smooth", "final"]
    assert len(report["residual"]["per_frame"]) == points.num_frames
    assert "/world/points" in entities(out / "recording.rrd")
    verify(out / "recording.rrd")
    # a second solve without a recording: the first one's would pass for its own
    assert _solve(tmp_path, out, "--no-recording") == 0
    assert not (out / "recording.rrd").exists()


def test_few_points_with_times_take_the_tracks_path(tmp_path, capsys):
    capture = _capture(tmp_path)
    out = tmp_path / "out"
    args = ["solve", "--cameras", str(tmp_path / "cameras.json"), "--tracks", str(tmp_path / "tracks.csv")]
    assert main([*args, "--out", str(out), "--no-recording"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["temporal"]["path"] == "tracks" and report["initialization"] is None
    checks = {c["name"]: c for c in report["temporal"]["checks"]}
    assert all(c["passed"] for c in checks.values())
    assert checks["track_distinctness"]["limit"] == 3.0  # more than 3 points: the search must win clearly
    points = read_points(out / "points3d.csv")
    index = capture.truth.index()
    truth = np.stack([capture.truth.xyz[index[(v, int(f))]] for v, f in zip(points.videos, points.frames, strict=True)])
    assert np.median(np.linalg.norm(points.xyz - truth, axis=-1)) < 1.0
    # W from the clocks: each frame between the bracketing frames of the other videos; none at the capture's ends
    sums = np.array([w.sum() for w in read_sequencing(out / "sequencing.json").weights])
    assert np.all((np.abs(sums - 1) < 1e-3) | (sums == 0)) and np.mean(sums > 0) > 0.9


def test_simulate_solve_evaluate_chain(tmp_path, capsys, shared_dir):
    mocap = shared_dir / "data" / "mocap" / "hdm05" / "HDM_dg_06-03_03_120.c3d"
    sim = tmp_path / "sim"
    assert main(["simulate", str(mocap), "--out", str(sim), "--length", "120", "--step", "2"]) == 0
    assert (
        main(
            [
                "solve",
                "--cameras",
                str(sim / "cameras.json"),
                "--tracks",
                str(sim / "tracks.csv"),
                "--out",
                str(sim),
                "--no-recording",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["evaluate", str(sim)]) == 0
    assert "<10:" in capsys.readouterr().out


def test_user_error_is_one_line_and_exit_code_2(tmp_path, capsys):
    _capture(tmp_path, frames=20, points=2)
    (tmp_path / "tracks.csv").write_text("video,frame,point,x,y\ncam0,0,p,1,2\nghost,0,p,1,2\n")
    code = main(
        [
            "solve",
            "--cameras",
            str(tmp_path / "cameras.json"),
            "--tracks",
            str(tmp_path / "tracks.csv"),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "tracks.csv:line 3: video 'ghost' is not in the cameras file" in err[0]
    assert not (tmp_path / "out" / "points3d.csv").exists()


def test_a_video_registration_left_unposed_is_left_out_of_the_solve(tmp_path, capsys, caplog):
    """The tracks register read name a video it could not pose (absent from cameras.json, unposed in
    register_report.json beside it): the solve leaves its rows out and says why, instead of refusing the file."""
    import logging

    capture = _capture(tmp_path, frames=40, points=4)
    rows = tmp_path / "tracks.csv"
    rows.write_text(rows.read_text() + "ghost,0,p0,1,2\nghost,1,p0,1,2\n")
    report = {"videos": [{"name": "ghost", "registered": 0, "failed": [{"reason": "no usable pair"}]}]}
    report["videos"] += [{"name": v.name, "registered": len(v.frames), "failed": []} for v in capture.cameras.videos]
    report["subject"] = {"failed": {"ghost": "not determined by the tracks"}}
    (tmp_path / "register_report.json").write_text(json.dumps(report))
    caplog.set_level(logging.WARNING)
    assert _solve(tmp_path, tmp_path / "out", "--no-recording") == 0
    said = [r.getMessage() for r in caplog.records if "'ghost' is left out" in r.getMessage()]
    assert len(said) == 1 and "registration did not pose it" in said[0] and "not determined by the tracks" in said[0]
    # without the report (or with the video posed there) the unknown name is still refused
    (tmp_path / "register_report.json").unlink()
    capsys.readouterr()
    assert _solve(tmp_path, tmp_path / "out2", "--no-recording") == 2
    assert "video 'ghost' is not in the cameras file" in capsys.readouterr().err


def test_solve_recovers_clocks_refines_and_adds_time_and_trust_columns(tmp_path):
    capture = _capture(tmp_path)
    out = tmp_path / "out"
    assert _solve(tmp_path, out, "--no-recording") == 0
    points = read_points(out / "points3d.csv")
    assert {"time", "condition", "residual_px", "flag"} <= set(points.extra)
    index = capture.truth.index()
    true_time = np.array(
        [capture.truth.extra["time"][index[(v, int(f))], 0] for v, f in zip(points.videos, points.frames, strict=True)]
    )
    # The simulation's decoder times are one shared clock: the recovered global time is that clock.
    assert np.median(np.abs(points.extra["time"][:, 0] - true_time)) < 0.25 / 30
    clocks = read_sequencing(out / "sequencing.json").extra["clocks"]
    assert len(clocks["videos"]) == len(capture.cameras.videos)
    report = json.loads((out / "report.json").read_text())
    assert report["temporal"]["refined"] and "flagged" in report["trust"]
    plain = tmp_path / "plain"
    assert (
        main(
            [
                "solve",
                "--cameras",
                str(tmp_path / "cameras.json"),
                "--tracks",
                str(tmp_path / "tracks.csv"),
                "--out",
                str(plain),
                "--no-recording",
                "--refinement",
                "none",
                "--trust",
                "balanced",
            ]
        )
        == 0
    )
    assert json.loads((plain / "report.json").read_text())["temporal"]["refined"] is False


def test_a_skeleton_naming_unknown_points_is_warned_about(tmp_path, caplog):
    from reconstruct.stage import SolveOptions, solve

    capture = _capture(tmp_path)
    known = capture.truth.point_names[0]
    options = SolveOptions(recording=None, skeleton=((known, "no_such_point"),))
    solve(tmp_path / "cameras.json", tmp_path / "tracks.csv", options)
    assert "skeleton: point(s) no_such_point not in the tracks: their bones are not drawn" in caplog.text


def test_videos_takes_names_separated_by_spaces_or_commas(tmp_path, capsys):
    """`solve --videos cam0 cam1` (as `track` and `label` take their videos) and `--videos cam0,cam1` alike."""
    from dynrecon.cli import build_parser
    from reconstruct.cli import _distinct_videos

    parser = build_parser("solve")
    common = ["solve", "--cameras", "c.json", "--tracks", "t.csv", "--out", str(tmp_path / "out")]
    spaced = parser.parse_args([*common, "--videos", "cam0", "cam1"])
    commas = parser.parse_args([*common, "--videos", "cam0,cam1,"])
    assert _distinct_videos(spaced.videos) == _distinct_videos(commas.videos) == ("cam0", "cam1")
    assert _distinct_videos(parser.parse_args(common).videos) == ()

    assert main([*common, "--videos", "cam0", "cam1,cam0"]) == 2
    assert "--videos names cam0 twice: give each video once" in capsys.readouterr().err
