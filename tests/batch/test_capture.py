"""A capture folder's manifest: its name becomes a folder under the batch's --out, so it must be one plain name."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from batch import read_capture
from dynrecon.errors import InputError


def _capture(tmp_path: Path, manifest: dict | None) -> Path:
    folder = tmp_path / "cap"
    folder.mkdir(parents=True)
    for name in ("cam0.mp4", "cam1.mp4"):
        (folder / name).write_bytes(b"")  # read_capture lists the videos; nothing reads them yet
    if manifest is not None:
        (folder / "capture.json").write_text(json.dumps(manifest))
    return folder


@pytest.mark.parametrize("name", ["../escaped", ".", "..", "a/b", "a\\b", " "])
def test_a_name_that_is_not_one_plain_folder_name_is_refused(tmp_path: Path, name: str) -> None:
    folder = _capture(tmp_path, {"name": name})
    with pytest.raises(InputError, match="capture name") as error:
        read_capture(folder)
    assert str(folder / "capture.json") in str(error.value) and "plain folder name" in str(error.value)


def test_the_folder_name_or_a_plain_name_is_kept(tmp_path: Path) -> None:
    assert read_capture(_capture(tmp_path / "a", None)).name == "cap"
    assert read_capture(_capture(tmp_path / "b", {"name": "day 1"})).name == "day 1"


def test_two_captures_of_one_name_keep_both_entries(tmp_path: Path) -> None:
    from batch.graph import _read_captures
    from batch.state import BatchState
    from dynrecon.pipeline import PipelineOptions

    first, second = _capture(tmp_path / "day1", None), _capture(tmp_path / "day2", None)
    state = BatchState(tmp_path / "out")
    good = _read_captures([first, second], state, tmp_path / "out", False, PipelineOptions())
    assert [c.folder for c in good] == [first]
    assert state.captures["cap"].workspace == str(tmp_path / "out" / "cap") and state.captures["cap"].status != "failed"
    clash = state.captures[str(second)]
    assert clash.status == "failed" and clash.stage == "read" and f"is also {first}" in (clash.error or "")


def test_a_batch_out_that_is_a_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from dynrecon.cli import main

    (tmp_path / "afile").write_text("x")
    assert main(["batch", str(_capture(tmp_path, None)), "--out", str(tmp_path / "afile")]) == 2
    assert "afile: cannot write here: it is a file, not a folder" in capsys.readouterr().err


def test_an_interrupted_capture_is_not_left_running(tmp_path: Path) -> None:
    from batch.state import BatchState

    state = BatchState(tmp_path)
    running, done = state.start("a", tmp_path / "a", tmp_path / "out" / "a"), state.start("b", tmp_path, None)
    running.status, running.stage = "running", "register"
    done.done()
    for status in (running, done):
        status.interrupt()
    state.save()
    again = BatchState(tmp_path).captures
    assert again["a"].status == "interrupted" and again["a"].stage == "register" and again["b"].status == "done"
