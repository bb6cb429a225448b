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
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from dynrecon.pipeline import State
from reconstruct.outputs.points import read_sequencing

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
