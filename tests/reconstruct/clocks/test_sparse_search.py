"""Tracks of every 4th frame (a detector run on a fraction of the frames): for one to three points the track search
interpolates across the tracks' own step (`search.sparse_tracks`), so the tracks path clocks the videos instead of
falling back to the seed solve."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from reconstruct.clocks.model import own_times
from reconstruct.clocks.search import sparse_tracks
from reconstruct.inputs import build_problem_checked
from reconstruct.stage import SolveOptions, solve
from sfm.cameras import read_cameras
from tracking.tracks import read_tracks, write_tracks

STEP = 4


@pytest.fixture(scope="module")
def sparse_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Five seconds of a drone seen by five phones (24-60 fps), its tracks kept on every 4th frame only."""
    out = tmp_path_factory.mktemp("flight")
    assert main(["simulate", "--mode", "flight", "--duration", "5", "--seed", "0", "--out", str(out)]) == 0
    tracks = read_tracks(out / "tracks.csv")
    write_tracks(out / "sparse.csv", tracks.take(np.flatnonzero(tracks.frame % STEP == 0)))
    return out


def test_sparse_tracks_are_told_from_dense_ones(sparse_flight: Path) -> None:
    cameras = read_cameras(sparse_flight / "cameras.json")
    dense, _ = build_problem_checked(cameras, read_tracks(sparse_flight / "tracks.csv"))
    sparse, _ = build_problem_checked(cameras, read_tracks(sparse_flight / "sparse.csv"))
    assert not sparse_tracks(dense, own_times(dense)[0])
    assert sparse_tracks(sparse, own_times(sparse)[0])


def test_one_point_tracked_on_every_fourth_frame_takes_the_tracks_path(sparse_flight: Path) -> None:
    result = solve(sparse_flight / "cameras.json", sparse_flight / "sparse.csv", SolveOptions(recording=None))
    assert result.report["temporal"]["path"] == "tracks", result.report["temporal"].get("reason")
    truth = {v["name"]: v for v in json.loads((sparse_flight / "clocks_truth.json").read_text())["videos"]}
    clocks = {c.name: c for c in result.temporal.clocks.videos}
    reference = result.temporal.clocks.reference
    for name, clock in clocks.items():
        expected = truth[name]["offset_s"] - truth[reference]["offset_s"]
        assert abs(clock.offset - expected) < 0.5 / truth[name]["fps"], name  # within half a frame
