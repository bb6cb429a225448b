"""`dynrecon label`: starts, prints the URL, serves, refuses a second server, stops cleanly on SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from dynrecon.cli import main
from dynrecon.lock import LOCK_NAME

REPO = Path(__file__).resolve().parents[2]


def test_label_command_serves_and_a_second_one_is_refused(
    workspace: Path, video: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    skeleton = tmp_path / "skeleton.json"
    skeleton.write_text(json.dumps({"points": ["head"], "connections": [["head", "tail"]]}))
    code = "import sys; from dynrecon.cli import main; sys.exit(main(sys.argv[1:]))"
    process = subprocess.Popen(
        [sys.executable, "-c", code, "label", str(workspace), "--videos", str(video), "--skeleton", str(skeleton)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        if not line:  # it exited: show why
            pytest.fail(process.stderr.read() if process.stderr else "no output")
        assert line.startswith("labeling page: http://127.0.0.1:"), line
        url = line.split()[2]
        with urllib.request.urlopen(url + "api/state", timeout=10) as response:
            state = json.loads(response.read())
        assert state["points"] == ["head", "tail"] and state["connections"] == [["head", "tail"]]
        assert [v["name"] for v in state["videos"]] == ["cam1"]

        # A second server on the same workspace: one line on stderr, exit status 2, the first one untouched.
        assert main(["label", str(workspace), "--videos", str(video)]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "another labeling server" in err and url in err
        with urllib.request.urlopen(url + "api/state", timeout=10) as response:
            assert response.status == 200
    finally:
        process.send_signal(signal.SIGTERM)  # like Ctrl+C: clean stop
        process.wait(timeout=20)
    assert process.returncode == 0
    assert not (workspace / LOCK_NAME).exists()
    # The videos and points are remembered for the next session.
    config = json.loads((workspace / "labeling.json").read_text())
    assert config["points"] == ["head", "tail"]
    assert Path(config["videos"]["cam1"]) == video.resolve()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--points", "a,b/c"], "invalid point name"),
        (["--skeleton", "missing.json"], "file not found"),
        (["--port", "70000"], "not a port number"),
    ],
)
def test_label_command_input_errors_are_one_line(
    workspace: Path, video: Path, args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["label", str(workspace), "--videos", str(video), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not (workspace / LOCK_NAME).exists()


def test_label_command_without_videos_says_how_to_give_them(
    workspace: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["label", str(workspace)]) == 2
    err = capsys.readouterr().err
    assert "no videos" in err and "--videos" in err
    assert not (workspace / LOCK_NAME).exists()


def test_bad_skeleton_file_names_the_problem(
    workspace: Path, video: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    skeleton = tmp_path / "bad.json"
    skeleton.write_text(json.dumps({"points": ["a"], "connections": [["a", "a"]]}))
    assert main(["label", str(workspace), "--videos", str(video), "--skeleton", str(skeleton)]) == 2
    err = capsys.readouterr().err
    assert str(skeleton) in err and "connection 0" in err


def test_video_that_opencv_cannot_read_is_an_input_error(
    workspace: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(os.urandom(2000))
    assert main(["label", str(workspace), "--videos", str(broken)]) == 2
    assert str(broken) in capsys.readouterr().err


def test_broken_labels_file_is_named_with_its_line(
    workspace: Path, video: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (workspace / "labels.csv").write_text("video,frame,point,x,y,source\ncam1,zero,head,1,2,label\n")
    assert main(["label", str(workspace), "--videos", str(video)]) == 2
    err = capsys.readouterr().err.strip()
    assert "labels.csv:line 2: frame 'zero' is not an integer" in err and "\n" not in err
    assert not (workspace / LOCK_NAME).exists()


def test_workspace_that_is_a_file_is_an_input_error(
    tmp_path: Path, video: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    not_a_folder = tmp_path / "ws.txt"
    not_a_folder.write_text("")
    assert main(["label", str(not_a_folder), "--videos", str(video)]) == 2
    assert "workspace is not a directory" in capsys.readouterr().err
