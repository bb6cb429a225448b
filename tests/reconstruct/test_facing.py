"""Cameras that face away from what they track (turned around, or poses stored as world_from_cam) are refused
before the solve, naming the videos."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main

WALKER = Path(__file__).resolve().parents[2] / "data_samples" / "walker.trc"


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("facing")
    assert main(["simulate", str(WALKER), "--out", str(out), "--length", "120"]) == 0
    return out


def _turned_around(capture: Path, videos: set[str], out: Path) -> Path:
    """cameras.json with `videos` turned 180 deg about their own vertical axis (same centre)."""
    document = json.loads((capture / "cameras.json").read_text())
    turn = np.diag([-1.0, 1.0, -1.0])
    for video in document["videos"]:
        if video["name"] in videos:
            for frame in video["frames"]:
                R, t = np.array(frame["R"]), np.array(frame["t"])
                frame["R"], frame["t"] = (turn @ R).tolist(), (turn @ t).tolist()
    out.write_text(json.dumps(document))
    return out


@pytest.mark.parametrize("videos", [{"cam0", "cam1", "cam2", "cam3"}, {"cam2"}])
def test_cameras_facing_away_are_named(
    capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], videos: set[str]
) -> None:
    cameras = _turned_around(capture, videos, tmp_path / "cameras.json")
    args = ["solve", "--cameras", str(cameras), "--tracks", str(capture / "tracks.csv"), "--out", str(tmp_path / "o")]
    assert main([*args, "--no-recording"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{cameras}: the tracked points lie behind the camera of" in err
    named = {name for name in ("cam0", "cam1", "cam2", "cam3") if f"{name} (" in err}
    assert named == videos and "world_from_cam" in err
    assert not (tmp_path / "o" / "points3d.csv").exists()


def test_the_true_poses_pass(capture: Path) -> None:
    from reconstruct.facing import check_facing
    from reconstruct.inputs import build_problem
    from sfm.cameras import read_cameras
    from tracking.tracks import read_tracks

    check_facing(build_problem(read_cameras(capture / "cameras.json"), read_tracks(capture / "tracks.csv")), "x")
