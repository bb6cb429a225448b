"""`dynrecon run` on a short cut of the embedded video sample: stages, skipping by hashes, accuracy, CLI."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from rrd_reader import entities, timelines, verify

from dynrecon import cli
from dynrecon.demo import pipeline_options
from dynrecon.errors import InputError
from dynrecon.pipeline import (
    STAGES,
    PipelineOptions,
    Stages,
    default_register,
    run_stages,
    score_against_truth,
)
from dynrecon.pipeline_state import inputs_key
from reconstruct.outputs.mocap import read_mocap
from reconstruct.outputs.points import FramePoints, read_points, read_sequencing, write_points
from sfm.calibration import read_calibration, write_toml
from sfm.cameras import read_cameras, write_cameras
from tracking.options import TrackOptions

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "video_sample"
STEP = 2  # the cut keeps every 2nd frame of each video: the whole walk at half the frame rates
CUT = {"cam0": 29, "cam1": 22, "cam2": 18}  # frames of each video in the cut


def _cut_sample(out: Path) -> dict[str, Path]:
    """Every STEP-th frame of each sample video (VP9 again), truth rows and true cameras renumbered to the cut's
    frames, and labels on every frame."""
    out.mkdir(parents=True, exist_ok=True)
    videos = {}
    for name, count in CUT.items():
        capture = cv2.VideoCapture(str(SAMPLE / f"{name}.mp4"))
        fps = capture.get(cv2.CAP_PROP_FPS)
        frames = [capture.read()[1] for _ in range(STEP * count)][::STEP]
        capture.release()
        path = out / f"{name}.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"vp09"), fps / STEP, frames[0].shape[1::-1])
        for frame in frames:
            writer.write(frame)
        writer.release()
        videos[name] = path
    truth = read_points(SAMPLE / "truth.csv")
    keep = [
        i
        for i, (v, f) in enumerate(zip(truth.videos, truth.frames, strict=True))
        if f % STEP == 0 and f // STEP < CUT[v]
    ]
    write_points(
        out / "truth.csv",
        FramePoints(
            videos=[truth.videos[i] for i in keep],
            frames=truth.frames[keep] // STEP,
            point_names=truth.point_names,
            xyz=truth.xyz[keep],
            observed=truth.observed[keep],
            extra={k: v[keep] for k, v in truth.extra.items()},
        ),
    )
    cameras = read_cameras(SAMPLE / "truth_cameras.json")
    for video in cameras.videos:
        video.frames = [
            replace(f, frame=f.frame // STEP)
            for f in video.frames
            if f.frame % STEP == 0 and f.frame // STEP < CUT[video.name]
        ]
    write_cameras(out / "truth_cameras.json", cameras)
    _write_labels(out)
    return videos


def _write_labels(out: Path) -> None:
    """Clicks on every frame of the cut: true projections plus 0.5 px noise (fixed seed).

    The sample's own labels (every 5th frame) fall on every 2.5th frame of this half-rate cut; the demo test
    (tests/reconstruct/test_demo.py) tracks them on a cut at the full rate. Here the tracker passes the labels through
    and the test checks the pipeline around them.
    """
    rng = np.random.default_rng(0)
    truth = read_points(out / "truth.csv")
    index = truth.index()
    with (out / "labels.csv").open("w", newline="") as target:
        writer = csv.writer(target, lineterminator="\n")
        writer.writerow(["video", "frame", "point", "x", "y", "source"])
        for video in read_cameras(out / "truth_cameras.json").videos:
            for camera in video.frames:
                xyz = truth.xyz[index[(video.name, camera.frame)]]
                x_img = (xyz @ camera.R.T + camera.t) @ camera.K.T
                uv = x_img[:, :2] / x_img[:, 2:] + rng.normal(0.0, 0.5, (len(xyz), 2))
                for name, (u, v) in zip(truth.point_names, uv, strict=True):
                    writer.writerow([video.name, camera.frame, name, f"{u:.3f}", f"{v:.3f}", "label"])


def _options(labels: Path) -> PipelineOptions:
    register = default_register()
    register.max_frames = 12
    # Small window and patch: the joints are ~10 px spheres on a textured background (measured: 1.7x more
    # tracked positions than the defaults, same accuracy).
    # The demo's clock settings: the sample's treadmill walk is periodic, and the default affine clocks came out a
    # stride off (median error 52 mm here instead of ~5 mm; see dynrecon.demo.pipeline_options).
    return PipelineOptions(
        register=register,
        track=TrackOptions(patch=11, win_size=11),
        labels=labels,
        skeleton=SAMPLE / "walker_skeleton.json",
        solve=pipeline_options(SAMPLE).solve,
    )


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    if not (SAMPLE / "cam0.mp4").is_file():
        pytest.skip("data_samples/video_sample is not generated")
    base = tmp_path_factory.mktemp("pipeline")
    videos = _cut_sample(base / "sample")
    ws = base / "ws"
    result = run_stages(list(videos.values()), ws, _options(base / "sample" / "labels.csv"))
    return base, videos, ws, result


@pytest.mark.slow
def test_first_run_runs_every_stage(first_run):
    _, _, ws, result = first_run
    assert [s.name for s in result.stages] == [s for s in STAGES if s != "subject"]  # no static video left out
    assert not any(s.skipped for s in result.stages)
    for name in (
        "register/cameras.json",
        "tracks.csv",
        "points3d.csv",
        "sequencing.json",
        "report.json",
        "recording.rrd",
        "points.trc",
        "points.c3d",
        "pipeline.json",
    ):
        assert (ws / name).is_file(), name
    state = json.loads((ws / "pipeline.json").read_text())
    assert set(state["stages"]) == set(STAGES) - {"subject"}
    # Every frame of the cut registered; the exports are the trajectories of all 18 joints resampled on the
    # recovered clock: a uniform grid over the clocks' time span at the export rate.
    points = read_points(ws / "points3d.csv")
    assert points.num_frames == sum(CUT.values())
    times = [f["time"] for f in read_sequencing(ws / "sequencing.json").extra["clocks"]["frames"]]
    for export in ("points.trc", "points.c3d"):
        mocap = read_mocap(ws / export)
        assert mocap.num_frames == int(np.floor((max(times) - min(times)) * mocap.rate + 1e-9)) + 1
        assert np.isfinite(mocap.xyz).all(axis=-1).mean() > 0.9
        assert mocap.marker_names == points.point_names
        assert mocap.rate == pytest.approx((30.0 + 24.0 + 20.0) / STEP)


def test_recording_has_background_videos_and_global_time(first_run):
    _, _, ws, _ = first_run
    found = entities(ws / "recording.rrd")
    parts = ("", "/image", "/image/tracks", "/image/reprojection")
    cameras = [f"/world/cameras/{v}{part}" for v in CUT for part in parts]
    for name in ("/world/background", "/world/points", "/metrics/residual", *cameras):
        assert name in found, name
    assert timelines(ws / "recording.rrd") == {"global_time", *(f"frame:{v}" for v in CUT)}
    checked = verify(ws / "recording.rrd")
    assert checked.returncode == 0, checked.stderr


def test_accuracy_against_truth(first_run):
    base, _, ws, _ = first_run
    sample = base / "sample"
    accuracy = score_against_truth(ws, sample / "truth.csv", sample / "truth_cameras.json")
    assert accuracy.count == sum(CUT.values()) * 18
    share = dict(zip(accuracy.thresholds, accuracy.share_under, strict=True))
    print(f"video sample cut, accuracy (mm): {accuracy.table()}")
    assert accuracy.median < 25.0
    assert share[50.0] > 0.8


def test_second_run_skips_then_new_labels_rerun_only_what_they_change(first_run):
    base, videos, ws, _ = first_run
    labels = base / "sample" / "labels.csv"
    again = run_stages(list(videos.values()), ws, _options(labels))
    assert all(s.skipped for s in again.stages), again.stages
    # Move one click by a pixel: register stays, track and everything after it reruns.
    lines = labels.read_text().splitlines()
    fields = lines[1].split(",")
    fields[3] = f"{float(fields[3]) + 1.0:.3f}"
    lines[1] = ",".join(fields)
    labels.write_text("\n".join(lines) + "\n")
    changed = run_stages(list(videos.values()), ws, _options(labels))
    skipped = {s.name: s.skipped for s in changed.stages}
    assert skipped == {"register": True, "track": False, "solve": False, "record": False, "export": False}


def test_changed_output_file_reruns_its_stage(first_run):
    base, videos, ws, _ = first_run
    (ws / "points.trc").write_text("edited by hand\n")
    result = run_stages(list(videos.values()), ws, _options(base / "sample" / "labels.csv"))
    assert {s.name for s in result.stages if not s.skipped} == {"export"}
    # Exported on the recovered clock: a uniform grid over the clocks' time span at the export rate.
    trc = read_mocap(ws / "points.trc")
    times = [f["time"] for f in read_sequencing(ws / "sequencing.json").extra["clocks"]["frames"]]
    assert trc.num_frames == int(np.floor((max(times) - min(times)) * trc.rate + 1e-9)) + 1


def test_cli_run_reports_skipped_stages(first_run, monkeypatch, capsys):
    base, videos, ws, _ = first_run
    assert "dynrecon.pipeline_cli" in cli.COMMAND_MODULES
    # The CLI's default track options differ from the test's: only track and later stages run again.
    code = cli.main(
        [
            "run",
            *map(str, videos.values()),
            "--out",
            str(ws),
            "--labels",
            str(base / "sample" / "labels.csv"),
            "--max-frames",
            "12",
            "--skeleton",
            str(SAMPLE / "walker_skeleton.json"),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "register  skipped (up to date)" in out
    assert "recording.rrd" in out
    assert (ws / "points3d.csv").is_file()


def test_cli_errors(tmp_path, monkeypatch, capsys):
    assert "dynrecon.pipeline_cli" in cli.COMMAND_MODULES
    code = cli.main(["run", str(tmp_path / "missing.mp4"), str(tmp_path / "b.mp4"), "--out", str(tmp_path / "ws")])
    assert code == 2
    assert "missing.mp4" in capsys.readouterr().err
    video = tmp_path / "v.mp4"
    video.write_bytes(b"")
    assert cli.main(["run", str(video), str(video), "--out", str(tmp_path / "ws"), "--track-window", "3"]) == 2
    assert "--track-window" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # --labels and --tracks are exclusive
        cli.main(["run", "a.mp4", "--out", "ws", "--labels", "l.csv", "--tracks", "t.csv"])


def test_labels_and_tracks_together_are_refused(tmp_path):
    video = tmp_path / "v.mp4"
    video.write_bytes(b"")
    (tmp_path / "l.csv").write_text("video,frame,point,x,y\n")
    (tmp_path / "t.csv").write_text("video,frame,point,x,y\n")
    with pytest.raises(InputError, match="not both"):
        run_stages([video], tmp_path / "ws", PipelineOptions(labels=tmp_path / "l.csv", tracks=tmp_path / "t.csv"))
    assert not (tmp_path / "ws").exists()  # refused before anything was written


# ----------------------------------------------------------------------------------------------------------
# `dynrecon run --calibration`: a lab calibration instead of the SfM registration


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory) -> Path:
    """A small simulated capture of static phones: three videos, labels, and calibration.toml from the truth."""
    from batch.synthetic import Inputs, SimulatedCaptureOptions, simulated_capture

    folder = tmp_path_factory.mktemp("calibrated") / "capture"
    return simulated_capture(folder, SimulatedCaptureOptions(seed=2, inputs=Inputs.LABELS, points=3, seconds=1.0))


def _run_calibrated(capture: Path, ws: Path, *extra: str) -> list[str]:
    videos = [str(p) for p in sorted(capture.glob("*.avi"))]
    labels = ["--labels", str(capture / "labels.csv")]
    return ["run", *videos, "--out", str(ws), *labels, "--calibration", str(capture / "calibration.toml"), *extra]


def test_run_with_a_calibration_equals_import_track_solve_by_hand(calibrated: Path, tmp_path: Path, capsys) -> None:
    from batch import read_capture, run_capture

    ws = tmp_path / "ws"
    assert cli.main(_run_calibrated(calibrated, ws)) == 0
    ran = capsys.readouterr().out
    assert "register " in ran and "skipped" not in ran
    # By hand: import-calibration, track, solve (the pipeline's solve draws no recording: its record stage does).
    hand = tmp_path / "hand"
    videos = [str(p) for p in sorted(calibrated.glob("*.avi"))]
    assert cli.main(["import-calibration", str(calibrated / "calibration.toml"), *videos, "--out", str(hand)]) == 0
    (hand / "labels.csv").write_bytes((calibrated / "labels.csv").read_bytes())
    assert cli.main(["track", str(hand), "--videos", *videos]) == 0
    solve = ["solve", "--cameras", str(hand / "cameras.json"), "--tracks", str(hand / "tracks.csv")]
    assert cli.main([*solve, "--out", str(hand), "--no-recording"]) == 0
    same = {"register/cameras.json": "cameras.json", "tracks.csv": "tracks.csv", "points3d.csv": "points3d.csv"}
    for ours, theirs in {**same, "sequencing.json": "sequencing.json"}.items():
        assert (ws / ours).read_bytes() == (hand / theirs).read_bytes(), ours
    for name in ("register/background.ply", "recording.rrd", "points.trc", "points.c3d"):
        assert (ws / name).is_file(), name
    # the calibration's world is in metres, and the exports say so (an SfM world's default label is mm)
    assert (ws / "points.trc").read_text().splitlines()[2].split("\t")[4] == "m"
    # The batch uses a capture folder's calibration the same way: the same bytes.
    assert all(not o.failed for o in run_capture(read_capture(calibrated), tmp_path / "batch"))
    for name in ("register/cameras.json", "tracks.csv", "points3d.csv", "sequencing.json", "points.trc", "points.c3d"):
        assert (tmp_path / "batch" / "capture" / name).read_bytes() == (ws / name).read_bytes(), name


def test_the_register_hash_covers_the_calibration_contents(calibrated: Path, tmp_path: Path) -> None:
    capture = shutil.copytree(calibrated, tmp_path / "capture")
    ws = tmp_path / "ws"
    options = PipelineOptions(labels=capture / "labels.csv", calibration=capture / "calibration.toml")
    videos = sorted(capture.glob("*.avi"))
    first = run_stages(videos, ws, options)
    assert [s.name for s in first.stages if not s.skipped] == ["register", "track", "solve", "record", "export"]
    assert all(s.skipped for s in run_stages(videos, ws, options).stages)
    # New bytes, same cameras: register runs again, and what it wrote is unchanged, so nothing after it does.
    with (capture / "calibration.toml").open("a") as handle:
        handle.write("# checked again on Tuesday\n")
    again = run_stages(videos, ws, options)
    assert {s.name: s.skipped for s in again.stages} == {
        "register": False,
        "track": True,
        "solve": True,
        "record": True,
        "export": True,
    }
    # A camera moved by 1 mm: everything that uses the cameras runs again.
    cameras = read_calibration(capture / "calibration.toml")
    assert cameras[0].t is not None
    cameras[0].t = cameras[0].t + 0.001
    write_toml(capture / "calibration.toml", cameras)
    moved = run_stages(videos, ws, options)
    assert [s.name for s in moved.stages if not s.skipped] == ["register", "solve", "record", "export"]


def test_run_takes_another_recordings_cameras_json_and_tracks_named_by_file(calibrated: Path, tmp_path: Path) -> None:
    """The cameras.json of a recording by the same static cameras (a board filmed before) as `--calibration`, and
    tracks whose video column names the files (`cam0.avi`): the same cameras and points as the lab's file."""
    first = tmp_path / "first"
    assert cli.main(_run_calibrated(calibrated, first)) == 0
    lines = (first / "tracks.csv").read_text().splitlines()
    by_file = [lines[0], *(line.replace(",", ".avi,", 1) for line in lines[1:])]
    (tmp_path / "tracks.csv").write_text("\n".join(by_file) + "\n")
    argv = _run_calibrated(calibrated, tmp_path / "second")
    argv[argv.index("--calibration") + 1] = str(first / "register" / "cameras.json")
    argv[argv.index("--labels") : argv.index("--labels") + 2] = ["--tracks", str(tmp_path / "tracks.csv")]
    assert cli.main(argv) == 0
    for name in ("register/cameras.json", "points3d.csv"):
        assert (tmp_path / "second" / name).read_bytes() == (first / name).read_bytes(), name
    # The simulated phones started 0.06-0.15 s apart. Declared synchronized (a false claim), the solve tests that
    # clock against its own, says they disagree, tries it, and keeps its own: the same points.
    argv[argv.index("--out") + 1] = str(tmp_path / "synced")
    assert cli.main([*argv, "--synchronized"]) == 0
    assert {v.clock_offset for v in read_cameras(tmp_path / "synced" / "register" / "cameras.json").videos} == {0.0}
    report = json.loads((tmp_path / "synced" / "report.json").read_text())
    assert report["clocks"]["registration_check"]["agree"] is False
    assert (
        report["temporal"]["registered_offsets"]["tried"]
        and report["temporal"]["registered_offsets"]["kept"] == "solve"
    )
    assert (tmp_path / "synced" / "points3d.csv").read_bytes() == (first / "points3d.csv").read_bytes()


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("missing", "calibration file not found"),
        ("folder", "is not a file: a calibration file was expected"),
        ("garbage", "lab.toml"),
        ("unknown format", "pass --calibration-format qca, toml, json, dannce or dlt"),
        ("other cameras", "match no camera name"),
        ("with intrinsics", "--intrinsics, --scale and --board (registration options) do not apply"),
        ("with a board", "--intrinsics, --scale and --board (registration options) do not apply"),
    ],
)
def test_run_calibration_errors_are_one_line(calibrated: Path, tmp_path: Path, capsys, case: str, reason: str) -> None:
    calibration = tmp_path / "lab.toml"
    extra: list[str] = []
    if case == "folder":
        calibration.mkdir()
    elif case == "garbage":
        calibration.write_bytes(bytes(range(256)) * 4)
    elif case == "unknown format":
        calibration = tmp_path / "lab.cal"
        calibration.write_bytes((calibrated / "calibration.toml").read_bytes())
    elif case == "other cameras":
        write_toml(calibration, read_calibration(calibrated / "calibration.toml")[:2])
    elif case == "with intrinsics":
        calibration.write_bytes((calibrated / "calibration.toml").read_bytes())
        extra = ["--intrinsics", str(calibration)]
    elif case == "with a board":
        calibration.write_bytes((calibrated / "calibration.toml").read_bytes())
        board = tmp_path / "charuco.toml"
        board.write_text("columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\n")
        extra = ["--board", str(board)]
    argv = _run_calibrated(calibrated, tmp_path / "ws", *extra)
    argv[argv.index("--calibration") + 1] = str(calibration)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"dynrecon run: error: {calibration}") and reason in last, err


def test_board_without_tracks_makes_the_track_stage(tmp_path: Path) -> None:
    """`run --board` with neither labels nor tracks: the board's corners found in the videos are WS/tracks.csv
    (the track stage, skipped when up to date); a tracks.csv the user put in WS is theirs and kept."""
    from board_video import render_board, write_video

    from tracking.charuco import read_charuco_board
    from tracking.tracks import read_tracks

    board = tmp_path / "charuco.toml"
    board.write_text(
        'columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n'
        "aruco_scale = 0.75\ninverted = true\n"
    )
    shifts = {"cam_a": 100, "cam_b": 160}
    videos = [
        write_video(
            tmp_path / f"{name}.avi",
            render_board(
                read_charuco_board(board),
                [np.array([[1.0, 0, shift + 5.0 * i], [0, 1.0, 20], [0, 0, 1]]) for i in range(3)],
                (640, 480),
            ),
        )
        for name, shift in shifts.items()
    ]
    options = PipelineOptions(register=replace(default_register(), board=board))
    stages = Stages(videos, tmp_path / "ws", options)
    tracks_path = stages.track()
    assert tracks_path == tmp_path / "ws" / "tracks.csv"
    tracks = read_tracks(tracks_path)
    assert len(tracks) == 2 * 3 * 12 and set(tracks.video) == {"cam_a", "cam_b"}
    assert [s.name for s in stages.result.stages] == ["track"] and not stages.result.stages[0].skipped
    again = Stages(videos, tmp_path / "ws", options)
    again.track()
    assert again.result.stages[0].skipped
    # a tracks.csv the user puts in WS after a board run is theirs too: kept, not overwritten with the corners
    (tmp_path / "ws" / "tracks.csv").write_text("video,frame,point,x,y\ncam_b,1,nose,3,4\n")
    Stages(videos, tmp_path / "ws", options).track()
    assert (tmp_path / "ws" / "tracks.csv").read_text() == "video,frame,point,x,y\ncam_b,1,nose,3,4\n"
    # the background registration of the pipeline looks for markers only where no board, tracks or labels come
    assert not options.background_register().find_markers and options.register.find_markers
    assert not PipelineOptions(tracks=tmp_path / "t.csv").background_register().find_markers
    assert PipelineOptions().background_register().find_markers
    assert not PipelineOptions().background_register(labels=True).find_markers
    own = tmp_path / "own"
    own.mkdir()
    (own / "tracks.csv").write_text("video,frame,point,x,y\ncam_a,0,nose,1,2\n")
    Stages(videos, own, options).track()
    assert (own / "tracks.csv").read_text() == "video,frame,point,x,y\ncam_a,0,nose,1,2\n"


def test_run_takes_dlt_calibrations_and_their_profiles(tmp_path: Path) -> None:
    """A DLTdv / easyWand calibration is told by its name; a --calibration-profile that is not there is refused
    before any stage runs."""
    from dynrecon.pipeline import _check_calibration
    from sfm.options import ImportCalibrationOptions
    from sfm.stage import RegisterOptions

    dlt = tmp_path / "wand_dltCoefs.csv"
    dlt.write_text("1,2\n" * 11, encoding="utf-8")
    _check_calibration(dlt, ImportCalibrationOptions(), RegisterOptions())
    missing = ImportCalibrationOptions(profile=tmp_path / "wand_profile.txt")
    with pytest.raises(InputError, match="camera profile not found"):
        _check_calibration(dlt, missing, RegisterOptions())


def test_an_intrinsics_file_edited_in_place_registers_again(tmp_path: Path) -> None:
    """The register stage's key holds the --intrinsics file's contents, not only its path: a focal edited in the
    same file must not leave the cameras registered with the old one (the subject stage already hashed it)."""
    from board_video import write_video

    videos = [write_video(tmp_path / f"{name}.avi", [np.full((48, 64, 3), 90, dtype=np.uint8)] * 2) for name in "ab"]
    intrinsics = tmp_path / "intrinsics.toml"
    intrinsics.write_text("[cam_a]\nmatrix = [[900.0, 0, 32], [0, 900, 24], [0, 0, 1]]\n", encoding="utf-8")
    options = PipelineOptions(register=replace(default_register(), intrinsics=intrinsics))
    files, settings, _ = Stages(videos, tmp_path / "ws", options)._register_inputs()
    before = inputs_key(files, settings)
    intrinsics.write_text("[cam_a]\nmatrix = [[1100.0, 0, 32], [0, 1100, 24], [0, 0, 1]]\n", encoding="utf-8")
    files, settings, _ = Stages(videos, tmp_path / "ws", options)._register_inputs()
    assert files["intrinsics"] == intrinsics and inputs_key(files, settings) != before


def test_tracks_given_from_inside_the_workspace_are_copied_before_any_stage(tmp_path: Path) -> None:
    """`run --tracks WS/register/marker_tracks.csv` (the next step `run` advises): the register stage, run again,
    rewrites its folder, so the tracks are copied into WS/tracks.csv before it and read from there."""
    from board_video import write_video

    videos = [write_video(tmp_path / f"{name}.avi", [np.full((48, 64, 3), 90, dtype=np.uint8)] * 2) for name in "ab"]
    markers = tmp_path / "ws" / "register" / "marker_tracks.csv"
    markers.parent.mkdir(parents=True)
    markers.write_text("video,frame,point,x,y,source\na,0,marker_0_0,1.0,2.0,marker\n", encoding="utf-8")
    stages = Stages(videos, tmp_path / "ws", PipelineOptions(tracks=markers))
    markers.unlink()  # as the register stage removes an earlier run's
    assert stages.options.tracks == tmp_path / "ws" / "tracks.csv"
    assert stages.track() == tmp_path / "ws" / "tracks.csv"
    assert "marker_0_0" in (tmp_path / "ws" / "tracks.csv").read_text(encoding="utf-8")


def test_without_labels_or_tracks_the_next_step_is_said_last(tmp_path: Path) -> None:
    """`run` with neither labels nor tracks only registers: the line saying what to do next is kept for the end of
    the run (after the stage list and warnings), not only logged on the way."""
    from board_video import write_video

    videos = [write_video(tmp_path / f"{name}.avi", [np.full((48, 64, 3), 90, dtype=np.uint8)] * 2) for name in "ab"]
    stages = Stages(videos, tmp_path / "ws")
    assert stages.track() is None
    assert stages.result.next_step is not None and f"dynrecon label {tmp_path / 'ws'}" in stages.result.next_step
    assert "--tracks" not in stages.result.next_step
    # the corners of the markers register found in view: the other way on, when the markers are the subject
    markers = tmp_path / "ws" / "register" / "marker_tracks.csv"
    markers.parent.mkdir(parents=True, exist_ok=True)
    markers.write_text("video,frame,point,x,y,source\n", encoding="utf-8")
    stages = Stages(videos, tmp_path / "ws")
    assert stages.track() is None and stages.result.next_step is not None
    assert stages.result.next_step.endswith(f"run it again with --tracks {tmp_path / 'ws' / 'marker_tracks.csv'}")
    assert (tmp_path / "ws" / "marker_tracks.csv").read_bytes() == markers.read_bytes()
    # a copy the user edited since (a false corner deleted) is kept aside when the next run copies again
    (tmp_path / "ws" / "marker_tracks.csv").write_text("video,frame,point,x,y,source\nedited\n", encoding="utf-8")
    assert Stages(videos, tmp_path / "ws").track() is None
    kept = list((tmp_path / "ws").glob("marker_tracks.before-*.csv"))
    assert len(kept) == 1 and kept[0].read_text(encoding="utf-8").endswith("edited\n")
    assert (tmp_path / "ws" / "marker_tracks.csv").read_bytes() == markers.read_bytes()


def test_a_registration_the_register_stage_did_not_write_is_kept_aside(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A user's `import-calibration ... --out WS/register`, then `run` without --calibration: the register stage
    writes WS/register/cameras.json again, and the user's is kept beside it with a warning, not replaced unseen;
    the stage's own file, run again (another key: --force), is replaced without a copy."""
    from board_video import write_video

    import dynrecon.pipeline as pipeline
    from sfm.stage import RegisterOptions

    videos = [write_video(tmp_path / f"{name}.avi", [np.full((48, 64, 3), 90, dtype=np.uint8)] * 2) for name in "ab"]
    cameras = tmp_path / "ws" / "register" / "cameras.json"
    cameras.parent.mkdir(parents=True)
    cameras.write_text('{"users": true}', encoding="utf-8")
    seen: list[str] = []

    def register(videos: list[Path], folder: Path, options: RegisterOptions) -> None:
        seen.append(cameras.read_text(encoding="utf-8"))
        cameras.write_text(f'{{"run": {len(seen)}}}', encoding="utf-8")
        (folder / "background.ply").write_text("ply", encoding="utf-8")

    monkeypatch.setattr(pipeline, "_register", register)
    Stages(videos, tmp_path / "ws").register()
    kept = list(cameras.parent.glob("cameras.before-*.json"))
    assert seen == ['{"users": true}'] and len(kept) == 1
    assert kept[0].read_text(encoding="utf-8") == '{"users": true}'
    Stages(videos, tmp_path / "ws", PipelineOptions(force=True)).register()
    assert len(seen) == 2 and len(list(cameras.parent.glob("cameras.before-*.json"))) == 1


def test_a_background_that_failed_is_not_mapped_again_on_the_same_inputs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A rig whose background gives no model (the subject's tracks pose it): each later `run` (new labels, a new
    solve option) mapped the background again for minutes to fail the same way. The failure is recorded with its
    inputs and report; the same inputs say it again at once, and --force, other inputs or a changed report redo it."""
    from board_video import write_video

    import dynrecon.pipeline as pipeline
    from sfm.stage import RegisterOptions, RegistrationError

    videos = [write_video(tmp_path / f"{name}.avi", [np.full((48, 64, 3), 90, dtype=np.uint8)] * 2) for name in "ab"]
    calls: list[int] = []

    def register(videos: list[Path], folder: Path, options: RegisterOptions) -> None:
        calls.append(1)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "register_report.json").write_text('{"ok": false}', encoding="utf-8")
        raise RegistrationError.of("only 0 of 2 videos registered", "no model", folder / "register_report.json")

    monkeypatch.setattr(pipeline, "_register", register)
    tracks = tmp_path / "tracks.csv"
    tracks.write_text("video,frame,point,x,y\na,0,p,1.0,2.0\n", encoding="utf-8")
    options = PipelineOptions(tracks=tracks)
    first = Stages(videos, tmp_path / "ws", options).register()
    again = Stages(videos, tmp_path / "ws", options).register()
    assert calls == [1] and first is not None and again is not None and str(again) == str(first)
    Stages(videos, tmp_path / "ws", replace(options, force=True)).register()
    assert len(calls) == 2
    (tmp_path / "ws" / "register" / "register_report.json").write_text('{"ok": false, "edited": 1}', encoding="utf-8")
    Stages(videos, tmp_path / "ws", options).register()
    assert len(calls) == 3
    with pytest.raises(RegistrationError, match="only 0 of 2 videos registered"):  # no tracks coming: said again
        Stages(videos, tmp_path / "ws2", PipelineOptions()).register()
    with pytest.raises(RegistrationError, match="only 0 of 2 videos registered"):
        Stages(videos, tmp_path / "ws2", PipelineOptions()).register()
    assert len(calls) == 4
