"""Few points whose tracks clock some videos only: the clock reference moves to the videos the track search links
(`search.linked_reference`), and the tracks path solves the clocked videos with the others left out
(`tracks_path.solve_without_unclocked`), instead of the seed solve, singular for one point (a 12-camera real rig's
single point ran past 15 minutes there)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from synthetic_motion import truth_array

from dynrecon.cli import main
from reconstruct.clocks.model import TimeSource
from reconstruct.clocks.search import PairHypothesis, linked_reference
from reconstruct.outputs.points import read_points
from reconstruct.stage import SolveOptions, solve
from reconstruct.temporal import TemporalOptions


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A drone 30-100 m from five phones for two seconds: cam0 tracks it in 4 frames, too few to clock it."""
    out = tmp_path_factory.mktemp("flight")
    assert main(["simulate", "--mode", "flight", "--duration", "2", "--seed", "0", "--out", str(out)]) == 0
    return out


def _median_error(sim: Path, result: object) -> float:
    truth = truth_array(result.problem, read_points(sim / "truth.csv"))  # type: ignore[attr-defined]
    error = np.linalg.norm(result.temporal.points - truth, axis=-1)  # type: ignore[attr-defined]
    return float(np.nanmedian(error[result.problem.observed]))  # type: ignore[attr-defined]


def _pair(v: int, u: int, distinctness: float) -> PairHypothesis:
    return PairHypothesis(v=v, u=u, alpha=0.0, beta=1.0, cost=1.0, runner_up=distinctness, samples=50)


def test_the_reference_moves_to_the_videos_distinct_pairs_link() -> None:
    decoder = [TimeSource.DECODER] * 5
    linked = [_pair(1, 2, 10.0), _pair(2, 3, 5.0), _pair(3, 4, 8.0), _pair(0, 1, 1.01)]  # 0-1 not distinct
    assert linked_reference(linked, 0, 5, decoder) == 1
    assert linked_reference([*linked, _pair(0, 4, 3.0)], 0, 5, decoder) == 0  # linked: the first video stays
    assert linked_reference([_pair(0, 1, 3.0), _pair(2, 3, 3.0)], 0, 5, decoder) == 0  # a tie keeps it
    nominal = [TimeSource.DECODER, TimeSource.NOMINAL, TimeSource.DECODER, TimeSource.DECODER, TimeSource.DECODER]
    assert linked_reference(linked, 0, 5, nominal) == 2  # the group's first video with decoder times


def test_a_video_the_tracks_cannot_clock_is_left_out_and_the_others_solved_on_the_tracks(
    flight: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        result = solve(flight / "cameras.json", flight / "tracks.csv", SolveOptions(recording=None))
    temporal = result.report["temporal"]
    assert temporal["left_out"] == ["cam0"] and temporal["tracks_path"]["failed"] == "identified"
    assert temporal["path"] == "tracks" and not result.seed.stages  # no seed solve
    assert result.problem.video_names == ["cam1", "cam2", "cam3", "cam4"]
    assert "cam0" not in {video for video in result.points.videos}
    assert any("no clock for video(s) cam0" in r.getMessage() and "left out" in r.getMessage() for r in caplog.records)
    # the seed solve on all five videos, the path taken before: several times further from the truth
    seed = solve(
        flight / "cameras.json",
        flight / "tracks.csv",
        SolveOptions(recording=None, temporal=TemporalOptions(tracks_path_max_points=0)),
    )
    assert seed.seed.stages
    mine, theirs = _median_error(flight, result), _median_error(flight, seed)
    assert mine < 0.4 * theirs, (mine, theirs)


def test_where_the_clocked_videos_fail_too_the_seed_solve_runs_and_says_why(
    flight: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import reconstruct.tracks_path as tracks_path

    original = tracks_path.solve_on_tracks

    def failing_without_cam0(problem, options, referee=None):  # type: ignore[no-untyped-def]
        if "cam0" in problem.video_names:
            return original(problem, options, referee)
        report = {"checks": [{"name": "tracks_fit", "passed": False}], "failed": "tracks_fit"}
        return tracks_path.TracksAttempt(temporal=None, seed=None, report=report)

    monkeypatch.setattr(tracks_path, "solve_on_tracks", failing_without_cam0)
    result = solve(flight / "cameras.json", flight / "tracks.csv", SolveOptions(recording=None))
    temporal = result.report["temporal"]
    assert result.seed.stages and "left_out" not in temporal
    assert temporal["tracks_path"]["without_unclocked"]["failed"] == "tracks_fit"
