"""`dynrecon solve` checks its recovered clocks against the offsets registration found (`clock_offset`)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from synthetic_motion import simulated_phones

from dynrecon.cli import main
from sfm.cameras import read_cameras, write_cameras


@pytest.fixture(scope="module")
def phones(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three static simulated phones (30, 25, 20 fps) with known clocks."""
    return simulated_phones(tmp_path_factory.mktemp("phones"))


def _solve_with_offsets(sim: Path, work: Path, shift: dict[str, float]) -> dict:
    clocks = json.loads((sim / "clocks_truth.json").read_text())
    cameras = read_cameras(sim / "cameras.json")
    for video in cameras.videos:
        truth = next(v for v in clocks["videos"] if v["name"] == video.name)
        video.clock_offset = truth["offset_s"] + shift.get(video.name, 0.0) + 5.0  # any common origin
    write_cameras(work / "cameras.json", cameras)
    assert (
        main(
            [
                "solve",
                "--cameras",
                str(work / "cameras.json"),
                "--tracks",
                str(sim / "tracks.csv"),
                "--out",
                str(work),
                "--no-recording",
            ]
        )
        == 0
    )
    return json.loads((work / "report.json").read_text())["clocks"]["registration_check"]


def test_registered_offsets_that_are_right_agree(phones: Path, tmp_path: Path) -> None:
    check = _solve_with_offsets(phones, tmp_path, {})
    assert check["agree"] and len(check["videos"]) == 2
    for video in check["videos"]:
        assert abs(video["difference_s"]) <= video["tolerance_s"] <= 0.051  # a frame at 20 fps


def test_a_wrong_registered_offset_is_named(phones: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    check = _solve_with_offsets(phones, tmp_path, {"cam2": 0.5})
    assert not check["agree"]
    by_video = {v["video"]: v for v in check["videos"]}
    assert not by_video["cam2"]["agree"] and abs(abs(by_video["cam2"]["difference_s"]) - 0.5) < 0.05
    assert "disagree with registration's offsets" in caplog.text
