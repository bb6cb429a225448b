"""Hostile input at the CLI: every case is exit status 2 and one line naming the file, never a traceback or abort.

A fixed corpus: huge frame numbers, numbers of thousands of digits, deeply nested JSON, folders where files are
expected, impossible options, outputs that cannot be written, and `dynrecon label` failing during its startup
(run in a subprocess: the abort it used to die with happens at interpreter exit).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from dynrecon.pipeline_state import State
from reconstruct.inputs import build_problem_checked
from reconstruct.outputs.points import read_points, read_sequencing
from sfm.calibration import read_calibration
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras
from sfm.video import probe_video
from tracking.labels import read_labels
from tracking.tracks import read_tracks

REPO = Path(__file__).resolve().parents[2]

HUGE_FRAMES = {"2^63": str(2**63), "10^20": str(10**20), "5000 digits": "9" * 5000}
DEEP_JSON = "[" * 100_000 + "]" * 100_000  # deeper than the JSON decoder's recursion limit
LONG_NUMBER_JSON = '{"videos": [], "x": ' + "1" * 5000 + "}"  # over Python's 4300-digit int limit


def _identity_frame(frame: object) -> dict:
    return {"frame": frame, "K": [[100, 0, 50], [0, 100, 50], [0, 0, 1]], "R": np.eye(3).tolist(), "t": [0, 0, 0]}


def _cameras(path: Path, frame: object = 0) -> Path:
    document = {"videos": [{"name": "a", "width": 100, "height": 100, "frames": [_identity_frame(frame)]}]}
    path.write_text(json.dumps(document))
    return path


def _tracks(path: Path, frame: str = "0") -> Path:
    path.write_text(f"video,frame,point,x,y\na,{frame},p,1,2\n")
    return path


def _labels(path: Path, frame: str = "0") -> Path:
    path.write_text(f"video,frame,point,x,y,source\ncam1,{frame},p,1,2,label\n")
    return path


def _video(path: Path, frames: int = 60) -> Path:
    # Noise frames decode slowly enough that the frame scan is still running when `label`'s startup fails.
    rng = np.random.default_rng(0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (320, 240))
    assert writer.isOpened()
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8))
    writer.release()
    return path


def _one_line_error(capsys: pytest.CaptureFixture[str], status: int, *names: str) -> str:
    err = capsys.readouterr().err
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


def _solve(cameras: Path, tracks: Path, out: Path, *extra: str) -> int:
    return main(
        ["-q", "solve", "--cameras", str(cameras), "--tracks", str(tracks), "--out", str(out), "--no-recording", *extra]
    )


# ---- frame numbers


@pytest.mark.parametrize("frame", list(HUGE_FRAMES.values()), ids=list(HUGE_FRAMES))
def test_huge_frame_in_tracks_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str], frame: str) -> None:
    tracks = _tracks(tmp_path / "tracks.csv", frame)
    status = _solve(_cameras(tmp_path / "cameras.json"), tracks, tmp_path / "out")
    line = _one_line_error(capsys, status, str(tracks), "line 2", "too large")
    assert len(line) < 400


@pytest.mark.parametrize("frame", list(HUGE_FRAMES.values()), ids=list(HUGE_FRAMES))
def test_huge_frame_in_labels_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str], frame: str) -> None:
    ws = tmp_path / "ws"
    ws.mkdir()
    labels = _labels(ws / "labels.csv", frame)
    video = _video(tmp_path / "cam1.avi", frames=2)
    status = main(["-q", "track", str(ws), "--videos", str(video)])
    _one_line_error(capsys, status, str(labels), "line 2", "too large")


@pytest.mark.parametrize("frame", [2**63, 10**20, 2**31], ids=["2^63", "10^20", "2^31"])
def test_huge_frame_in_cameras_json(tmp_path: Path, capsys: pytest.CaptureFixture[str], frame: int) -> None:
    cameras = _cameras(tmp_path / "cameras.json", frame)
    status = _solve(cameras, _tracks(tmp_path / "tracks.csv"), tmp_path / "out")
    _one_line_error(capsys, status, str(cameras), "too large")


def test_huge_frame_in_points_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "points3d.csv").write_text(f"video,frame,point,x,y,z,observed\na,{2**63},p,1,2,3,1\n")
    (tmp_path / "truth.csv").write_text("video,frame,point,x,y,z,observed\na,0,p,1,2,3,1\n")
    status = main(["-q", "evaluate", str(tmp_path)])
    _one_line_error(capsys, status, "points3d.csv", "line 2", "too large")


# ---- JSON: thousands of digits, deep nesting, folders


@pytest.mark.parametrize("text", [LONG_NUMBER_JSON, DEEP_JSON], ids=["5000 digits", "deeply nested"])
def test_hostile_cameras_json(tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str) -> None:
    cameras = tmp_path / "cameras.json"
    cameras.write_text(text)
    status = _solve(cameras, _tracks(tmp_path / "tracks.csv"), tmp_path / "out")
    _one_line_error(capsys, status, str(cameras), "invalid JSON")


def test_tracks_given_for_the_cameras_are_named_a_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tracks = _tracks(tmp_path / "tracks.csv")
    status = _solve(tracks, tracks, tmp_path / "out")
    _one_line_error(
        capsys, status, str(tracks), "is a CSV file (its first line: 'video,frame,point,x,y", "cameras.json"
    )


@pytest.mark.parametrize(
    "text",
    [LONG_NUMBER_JSON, DEEP_JSON, '{"points": ["a"], "connections": [' + "[" * 900 + "]" * 900 + "]}"],
    ids=["5000 digits", "deeply nested", "nested pair"],
)
def test_hostile_skeleton(tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str) -> None:
    skeleton = tmp_path / "skeleton.json"
    skeleton.write_text(text)
    status = _solve(tmp_path / "cameras.json", tmp_path / "tracks.csv", tmp_path / "out", "--skeleton", str(skeleton))
    _one_line_error(capsys, status, str(skeleton))


@pytest.mark.parametrize(
    "text",
    [LONG_NUMBER_JSON, DEEP_JSON, json.dumps({"frames": [{"video": "a", "frame": 2**63, "neighbours": []}]})],
    ids=["5000 digits", "deeply nested", "frame 2^63"],
)
def test_hostile_sequencing_json(tmp_path: Path, text: str) -> None:
    path = tmp_path / "sequencing.json"
    path.write_text(text)
    with pytest.raises(InputError, match=r"sequencing\.json") as caught:
        read_sequencing(path)
    assert "\n" not in str(caught.value) and len(str(caught.value)) < 400


@pytest.mark.parametrize("role", ["cameras", "tracks", "skeleton"])
def test_input_that_is_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str], role: str) -> None:
    paths = {"cameras": _cameras(tmp_path / "cameras.json"), "tracks": _tracks(tmp_path / "tracks.csv")}
    folder = tmp_path / f"{role}.folder"
    folder.mkdir()
    paths[role] = folder
    extra = ["--skeleton", str(folder)] if role == "skeleton" else []
    status = _solve(paths["cameras"], paths["tracks"], tmp_path / "out", *extra)
    _one_line_error(capsys, status, str(folder))


@pytest.mark.parametrize(
    "document",
    [
        "[" * 100_000,
        "1" * 5000,
        "[1, 2]",
        '{"stages": [1]}',
        '{"stages": {"solve": 3}}',
        '{"stages": {"solve": {"inputs": 1}}}',
        '{"stages": {"solve": {"inputs": "k", "outputs": [1]}}}',
    ],
    ids=["deep", "digits", "list", "stages list", "entry int", "inputs int", "outputs list"],
)
def test_corrupted_pipeline_json_reruns_the_stage(tmp_path: Path, document: str) -> None:
    (tmp_path / "pipeline.json").write_text(document)
    state = State(tmp_path)  # warns instead of crashing
    assert not state.up_to_date("solve", "k", tmp_path)


# ---- options and outputs


def test_zero_iterations(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = _solve(tmp_path / "cameras.json", tmp_path / "tracks.csv", tmp_path / "out", "--max-iterations", "0")
    _one_line_error(capsys, status, "--max-iterations 0")


@pytest.fixture
def unwritable(tmp_path: Path) -> Path:
    """An output folder that cannot be created: its parent is a regular file (root ignores chmod, not this)."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    return blocker / "sub"


def test_solve_into_unwritable_folder(tmp_path: Path, unwritable: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The inputs are missing: the output folder is checked first, before any work.
    status = _solve(tmp_path / "cameras.json", tmp_path / "tracks.csv", unwritable)
    _one_line_error(capsys, status, str(unwritable), "cannot write")


def test_simulate_into_unwritable_folder(unwritable: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = main(["-q", "simulate", "--mode", "flight", "--out", str(unwritable)])
    _one_line_error(capsys, status, str(unwritable), "cannot write")


def test_track_into_unwritable_folder(tmp_path: Path, unwritable: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ws = tmp_path / "ws"
    ws.mkdir()
    _labels(ws / "labels.csv")
    status = main(
        [
            "-q",
            "track",
            str(ws),
            "--videos",
            str(_video(tmp_path / "cam1.avi", frames=2)),
            "--out",
            str(unwritable / "tracks.csv"),
        ]
    )
    _one_line_error(capsys, status, str(unwritable), "cannot write")


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes into read-only folders")
def test_solve_into_read_only_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    out.chmod(0o555)
    try:
        status = _solve(tmp_path / "cameras.json", tmp_path / "tracks.csv", out)
    finally:
        out.chmod(0o755)
    _one_line_error(capsys, status, str(out), "cannot write")


# ---- `dynrecon label` failing after its frame scan started


def test_label_startup_failures_exit_2_without_abort(tmp_path: Path) -> None:
    video = _video(tmp_path / "cam1.avi")
    cases: dict[str, tuple[list[str], str]] = {}

    def workspace(name: str) -> Path:
        ws = tmp_path / name
        ws.mkdir()
        return ws

    bad = workspace("bad_value")
    _labels(bad / "labels.csv", "zero")
    cases["bad value"] = ([str(bad)], "labels.csv:line 2")
    huge = workspace("huge_frame")
    _labels(huge / "labels.csv", str(2**63))
    cases["huge frame"] = ([str(huge)], "labels.csv:line 2")
    folder = workspace("labels_folder")
    (folder / "labels.csv").mkdir()
    cases["labels.csv is a folder"] = ([str(folder)], "labels.csv")
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    cases["port in use"] = ([str(workspace("port")), "--port", str(port)], f"127.0.0.1:{port}")
    # 192.0.2.1 (TEST-NET-1) is not an address of this machine: bind() fails with EADDRNOTAVAIL.
    cases["unreachable host"] = ([str(workspace("host")), "--host", "192.0.2.1"], "192.0.2.1")
    try:
        processes = {
            name: subprocess.Popen(
                [sys.executable, "-m", "dynrecon", "-q", "label", *args, "--videos", str(video)],
                cwd=REPO,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for name, (args, _) in cases.items()
        }
        results = {name: (p.wait(timeout=60), p.communicate()[1]) for name, p in processes.items()}
    finally:
        busy.close()
    for name, (status, err) in results.items():
        lines = err.strip().splitlines()
        assert status == 2 and len(lines) == 1, f"{name}: exit {status}\n{err}"
        assert lines[0].startswith("dynrecon label: error:") and cases[name][1] in lines[0], f"{name}: {err}"


# ---- spreadsheet CSVs: BOM, CRLF, exact line numbers


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r"], ids=["LF", "CRLF", "CR"])
def test_csv_readers_accept_bom_and_line_ends(tmp_path: Path, newline: str) -> None:
    tracks = tmp_path / "tracks.csv"
    tracks.write_bytes(newline.join(["\ufeffvideo,frame,point,x,y", "a,0,p,1,2", "a,1,p,3,4", ""]).encode())
    read = read_tracks(tracks)
    assert read.video == ["a", "a"] and read.line is not None and read.line.tolist() == [2, 3]
    labels = tmp_path / "labels.csv"
    labels.write_bytes(newline.join(["\ufeffvideo,frame,point,x,y,source", "a,0,p,1,2,label", ""]).encode())
    assert read_labels(labels)[("a", 0, "p")].xy == (1.0, 2.0)


def _unterminated_quote_on_line_4(header: str, row: str, rows: int) -> str:
    return "\n".join([header, row, row.replace(",0,", ",1,", 1), '"' + row.replace(",0,", ",2,", 1)] + [row] * rows)


# 20000 rows: the quoted cell outgrows csv's field size limit before the end of the file
@pytest.mark.parametrize("rows", [900, 20000])
@pytest.mark.parametrize("reader", ["tracks", "labels", "points"])
def test_unterminated_quote_names_its_line(tmp_path: Path, reader: str, rows: int) -> None:
    path = tmp_path / f"{reader}.csv"
    call: Callable[[Path], object]
    if reader == "tracks":
        path.write_text(_unterminated_quote_on_line_4("video,frame,point,x,y", "a,0,p,1,2", rows))
        call = read_tracks
    elif reader == "labels":
        path.write_text(_unterminated_quote_on_line_4("video,frame,point,x,y,source", "a,0,p,1,2,label", rows))
        call = read_labels
    else:
        path.write_text(_unterminated_quote_on_line_4("video,frame,point,x,y,z,observed", "a,0,p,1,2,3,1", rows))
        call = read_points
    with pytest.raises(InputError, match=r":line 4: ") as caught:
        call(path)
    assert "\n" not in str(caught.value)


def test_csv_errors_name_the_line_of_the_row(tmp_path: Path) -> None:
    path = tmp_path / "tracks.csv"
    path.write_text("\r\n".join(["\ufeffvideo,frame,point,x,y", 'a,0,p,"1",2', "", "a,1,p,1", "a,9,p,1,2", ""]))
    with pytest.raises(InputError, match=r":line 4: expected 5 fields"):
        read_tracks(path)
    path.write_text("\r\n".join(["\ufeffvideo,frame,point,x,y", 'a,0,p,"1",2', "", "a,1,p,1,2", ""]))
    assert read_tracks(path).line.tolist() == [2, 4]  # type: ignore[union-attr]


# ---- observations and labels outside the image


def _two_videos() -> CameraSet:
    def frame(number: int, x: float) -> FrameCamera:
        K = np.array([[1000.0, 0, 499.5], [0, 1000.0, 499.5], [0, 0, 1]])
        return FrameCamera(frame=number, K=K, R=np.eye(3), t=np.array([x, 0.0, 10.0]))

    return CameraSet(
        videos=[
            VideoCameras(name=name, width=1000, height=800, frames=[frame(0, x), frame(1, x)])
            for name, x in (("a", 0.0), ("b", 1.0))
        ]
    )


@pytest.mark.parametrize("x, y", [(99999, 99999), (-101, 5), (5, 880), (1e308, 0)])
def test_observations_outside_the_image_are_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, x: float, y: float
) -> None:
    path = tmp_path / "tracks.csv"
    path.write_text(f"video,frame,point,x,y\na,0,p,10,20\nb,0,p,30,40\na,1,p,{x},{y}\nb,1,p,-99,879\n")
    with caplog.at_level("WARNING"):
        problem, rejected = build_problem_checked(_two_videos(), read_tracks(path))
    assert rejected.count == 1 and rejected.first == f"{path}:line 4"
    assert rejected.to_json() == {
        "outside_image": 1,
        "first": f"{path}:line 4",
        "margin": 0.1,
        "isolated_spikes": 0,
        "on_unposed_frames": 0,
    }
    assert int(problem.observed.sum()) == 3  # the row at the edge's margin (-99, 879) stays
    warning = [r.getMessage() for r in caplog.records if "outside the image" in r.getMessage()]
    assert len(warning) == 1 and "line 4" in warning[0] and "1 observation(s)" in warning[0]


def test_valid_observations_reject_nothing(tmp_path: Path) -> None:
    path = tmp_path / "tracks.csv"
    path.write_text("video,frame,point,x,y\na,0,p,-0.5,-0.5\nb,0,p,999.5,799.5\na,1,p,500,400\n")
    problem, rejected = build_problem_checked(_two_videos(), read_tracks(path))
    assert rejected.count == 0 and rejected.first is None and int(problem.observed.sum()) == 3


def test_track_refuses_a_label_outside_the_image(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ws = tmp_path / "ws"
    ws.mkdir()
    labels = ws / "labels.csv"
    labels.write_text("video,frame,point,x,y,source\ncam1,0,p,10,20,label\ncam1,1,p,99999,99999,label\n")
    video = _video(tmp_path / "cam1.avi", frames=2)
    status = main(["-q", "track", str(ws), "--videos", str(video)])
    line = _one_line_error(capsys, status, str(labels), "line 3", "outside the 320x240 image")
    assert "99999" in line
    assert not (ws / "tracks.csv").exists()


# ---- cameras.json and calibration files: finite but absurd values


def _camera_document(**changes: object) -> dict:
    frame = _identity_frame(0) | {"dist": [0.0, 0.0, 0.0, 0.0]}
    frame.update(changes)
    return {"videos": [{"name": "a", "width": 100, "height": 100, "frames": [frame]}]}


ABSURD_CAMERAS = {
    "focal 1e-300": {"K": [[1e-300, 0, 50], [0, 100, 50], [0, 0, 1]]},
    "focal 1e308": {"K": [[100, 0, 50], [0, 1e308, 50], [0, 0, 1]]},
    "principal point 1e300": {"K": [[100, 0, 1e300], [0, 100, 50], [0, 0, 1]]},
    "k1 1e308": {"dist": [1e308, 0.0, 0.0, 0.0]},
    "t 1e308": {"t": [1e308, 0, 0]},
    "t 1e9": {"t": [0, 0, 1e9]},
    "R det -1": {"R": np.diag([1.0, 1.0, -1.0]).tolist()},
    "R scaled": {"R": (np.eye(3) * (1 + 1e-4)).tolist()},
}


@pytest.mark.parametrize("changes", list(ABSURD_CAMERAS.values()), ids=list(ABSURD_CAMERAS))
def test_absurd_cameras_json(tmp_path: Path, capsys: pytest.CaptureFixture[str], changes: dict) -> None:
    cameras = tmp_path / "cameras.json"
    cameras.write_text(json.dumps(_camera_document(**changes)))
    status = _solve(cameras, _tracks(tmp_path / "tracks.csv"), tmp_path / "out")
    _one_line_error(capsys, status, str(cameras), "video 'a' frame 0")


def test_plausible_cameras_json_reads(tmp_path: Path) -> None:
    cameras = tmp_path / "cameras.json"
    cameras.write_text(json.dumps(_camera_document(t=[1e8, -1e8, 5.0], dist=[-0.4, 0.2, 0.001, -0.001, 999.0])))
    assert read_cameras(cameras).videos[0].frames[0].dist is not None


@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        ("[[1e308, 0, 50], [0, 100, 50], [0, 0, 1]]", r"\"K\" fx"),
        ("[[0.5, 0, 50], [0, 0.5, 50], [0, 0, 1]]", r"\"K\" fx"),
        # a mutation sweep (2026-11-30): written to cameras.json, then refused naming that file, not the user's
        ("[[100, 0, 50], [0, 100, 50], [0, 0, 1e30]]", r"\"K\" .* is not a camera matrix \(it must read"),
    ],
)
def test_absurd_calibration_toml(tmp_path: Path, matrix: str, message: str) -> None:
    path = tmp_path / "calib.toml"
    path.write_text(
        f'[cam_1]\nname = "a"\nsize = [100, 100]\nmatrix = {matrix}\ndistortions = [0, 0, 0, 0]\n'
        "rotation = [0, 0, 0]\ntranslation = [0, 0, 1]\n"
    )
    with pytest.raises(InputError, match=r"calib\.toml:camera 'a': " + message):
        read_calibration(path)


# ---- sequencing.json weights


@pytest.mark.parametrize("weight", ["NaN", "-0.5", "Infinity"])
def test_sequencing_weights_must_be_finite_and_non_negative(tmp_path: Path, weight: str) -> None:
    path = tmp_path / "sequencing.json"
    path.write_text(
        '{"frames": [{"video": "a", "frame": 0, "neighbours": [{"video": "b", "frame": 0, "weight": '
        + weight
        + '}]}, {"video": "b", "frame": 0, "neighbours": []}]}'
    )
    with pytest.raises(InputError, match=r"sequencing\.json:video 'a' frame 0: weight .* is not a finite number"):
        read_sequencing(path)


# ---- video names become folder names


@pytest.mark.parametrize("name", ["...mp4", "..avi", "a\x07b.mp4"], ids=["stem ..", "stem .", "control character"])
def test_video_name_is_checked_before_it_becomes_a_path(tmp_path: Path, name: str) -> None:
    video = _video(tmp_path / name, frames=2)
    with pytest.raises(InputError, match=r"video name .* \(rename the video file") as caught:
        probe_video(video)
    assert "\n" not in str(caught.value).replace("\\n", "")


def test_register_refuses_a_video_named_dot_dot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    videos = [_video(tmp_path / "...avi", frames=2), _video(tmp_path / "cam1.avi", frames=2)]
    status = main(["-q", "register", *map(str, videos), "--out", str(tmp_path / "ws")])
    _one_line_error(capsys, status, "video name '..' is only dots", "rename")
    assert not list((tmp_path / "ws").glob("*.jpg"))
