"""Few points whose tracks do not single out the clocks: cameras.json's clock offsets (registration's, or declared
synchronized) are tested against each pair's track search (reconstruct/clocks/given.py) and, where no pair refutes
them, the trajectories are fitted on them (`tracks_path.solve_on_given_clocks`) instead of the seed solve, which
stalls on one point over long videos."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from synthetic_motion import truth_array

from dynrecon.cli import main
from reconstruct.clocks.given import PairVerdict, corroborated, pair_verdicts
from reconstruct.clocks.model import own_times
from reconstruct.clocks.ray_gap import ray_gap_px
from reconstruct.clocks.search import SearchOptions
from reconstruct.inputs import build_problem_checked
from reconstruct.outputs.points import read_points
from reconstruct.registered_offsets import PATH
from reconstruct.solver.problem import Problem
from reconstruct.stage import SolveOptions, solve
from sfm.cameras import CameraSet, read_cameras
from tracking.tracks import read_tracks

WRONG_S = 0.5  # one video's declared offset this far off: 15-30 frames of a fast, far flight


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two seconds of a drone 30-100 m from five phones, 1.5 px noise and false detections: too few samples per
    video (4-50) for the track search to clock every video, so the tracks path fails its 'identified' check."""
    out = tmp_path_factory.mktemp("flight")
    args = ["simulate", "--mode", "flight", "--duration", "2", "--seed", "0", "--out", str(out)]
    assert main(args) == 0
    return out


def _cameras(sim: Path, wrong: float = 0.0) -> CameraSet:
    """cameras.json with the true clock offsets (any common origin), the second video's `wrong` seconds off."""
    truth = json.loads((sim / "clocks_truth.json").read_text())
    cameras = read_cameras(sim / "cameras.json")
    for i, video in enumerate(cameras.videos):
        offset = next(v["offset_s"] for v in truth["videos"] if v["name"] == video.name)
        video.clock_offset = offset + 3.0 + (wrong if i == 1 else 0.0)
    return cameras


def _problem(sim: Path) -> Problem:
    problem, _ = build_problem_checked(read_cameras(sim / "cameras.json"), read_tracks(sim / "tracks.csv"))
    return problem


def _true_offsets(sim: Path, problem: Problem) -> np.ndarray:
    truth = json.loads((sim / "clocks_truth.json").read_text())
    return np.array([next(v["offset_s"] for v in truth["videos"] if v["name"] == n) for n in problem.video_names])


def _error(sim: Path, result_points: np.ndarray, problem: Problem) -> float:
    truth = truth_array(problem, read_points(sim / "truth.csv"))
    error = np.linalg.norm(result_points - truth, axis=-1)
    return float(np.nanmedian(error[problem.observed]))


def test_no_pair_refutes_the_true_offsets_and_some_refute_a_wrong_one(flight: Path) -> None:
    problem = _problem(flight)
    own, _ = own_times(problem)
    offsets = _true_offsets(flight, problem)
    verdicts = pair_verdicts(problem, own, offsets, SearchOptions())
    assert len(verdicts) >= 6  # cam0's 4 samples overlap no other video enough for a search
    assert not any(v.refutes for v in verdicts)
    offsets[1] += WRONG_S
    wrong = [v for v in pair_verdicts(problem, own, offsets, SearchOptions()) if v.refutes]
    assert wrong, "a video half a second off must be refuted by some distinct pair"
    assert all(problem.video_names[1] in (v.v, v.u) for v in wrong)
    for v in wrong:  # its best offset is near the true one (the coarse grid's), not the given one
        assert abs(v.best_s - (v.given_s + (WRONG_S if v.u == problem.video_names[1] else -WRONG_S))) < 0.1


def test_the_ray_gap_is_smallest_at_the_true_offsets_also_on_sparse_tracks(flight: Path) -> None:
    problem = _problem(flight)
    own, _ = own_times(problem)
    offsets = _true_offsets(flight, problem)
    right = own + offsets[problem.video_index]
    gap = ray_gap_px(problem, right)
    assert 0.5 < gap < 5.0  # 1.5 px noise on each of two rays
    for shift in (0.05, WRONG_S):  # one video off moves 8 of the 20 ordered pairs' gaps: the median rises
        moved = right.copy()
        moved[problem.video_index == 1] += shift
        assert ray_gap_px(problem, moved) > 1.2 * gap
    # tracks of every other sample: interpolated across the untracked frames, not NaN
    sparse = problem.uv.copy()
    for v in range(len(problem.video_names)):
        seen = np.flatnonzero((problem.video_index == v) & problem.observed[:, 0])
        sparse[seen[1::2]] = np.nan
    thinned = Problem(**{**problem.__dict__, "uv": sparse})
    assert 0.5 < ray_gap_px(thinned, right) < 2 * gap


def test_one_point_is_fitted_on_the_given_offsets_without_the_seed_solve(flight: Path) -> None:
    options = SolveOptions(recording=None)
    given = solve(_cameras(flight), flight / "tracks.csv", options)
    report = given.report["temporal"]
    assert report["path"] == PATH, report.get("reason")
    assert report["tracks_path"]["failed"] == "identified"
    assert not given.seed.stages and "w_step" not in given.report["timings"]  # no seed solve
    checks = {c["name"]: c for c in report["checks"]}
    assert checks["given_offsets"]["passed"] and checks["tracks_fit"]["passed"]
    # without the offsets the tracks clock four videos only: cam0 (4 samples) is left out of the solve; the given
    # offsets keep all five, as close to the truth
    none = solve(read_cameras(flight / "cameras.json"), flight / "tracks.csv", options)
    assert none.report["temporal"]["left_out"] == ["cam0"] and not none.seed.stages
    assert len(given.problem.video_names) == 5 and "cam0" not in none.problem.video_names
    mine, theirs = (
        _error(flight, given.temporal.points, given.problem),
        _error(flight, none.temporal.points, none.problem),
    )
    assert mine < 1.2 * theirs, (mine, theirs)


def test_wrong_given_offsets_are_refused_and_the_tracks_decide(flight: Path) -> None:
    result = solve(_cameras(flight, wrong=WRONG_S), flight / "tracks.csv", SolveOptions(recording=None))
    report = result.report["temporal"]
    assert report["path"] != PATH
    tried = report["tracks_path"]["registered_offsets"]
    assert tried["failed"] == "given_offsets"
    # nor taken after the seed solve: the same pairs refute them there
    assert report[PATH]["criterion"] == "given_offsets" and report[PATH]["kept"] == "solve"
    assert report["left_out"] == ["cam0"]  # the videos the tracks clock, solved on their clocks


def test_a_pair_refutes_only_with_a_clearly_distinct_search_outside_the_basin() -> None:
    def verdict(distinctness: float, given_cost: float, given_s: float = 0.5) -> PairVerdict:
        return PairVerdict(
            v="a",
            u="b",
            given_s=given_s,
            best_s=0.0,
            best_cost=1.0,
            given_cost=given_cost,
            distinctness=distinctness,
            basin_s=0.1,
        )

    assert verdict(distinctness=10.0, given_cost=60.0).refutes  # a simulated video 0.5 s off
    # the Pose2Sim lab's pairs on cameras a degree off: a wrong best at distinctness 1.5, registration's right
    # offsets 1.6-3x its cost
    assert not verdict(distinctness=1.5, given_cost=3.0).refutes
    assert not verdict(distinctness=10.0, given_cost=1.5).refutes  # the given offset about as good
    assert not verdict(distinctness=10.0, given_cost=60.0, given_s=0.05).refutes  # within the best's basin
    assert not verdict(distinctness=10.0, given_cost=math.inf).refutes  # no overlap there: no evidence


def _verdict(v: str, u: str, given: float, best: float, distinctness: float = 10.0) -> PairVerdict:
    return PairVerdict(
        v=v, u=u, given_s=given, best_s=best, best_cost=1.0, given_cost=5.0, distinctness=distinctness, basin_s=0.133
    )


def test_a_refuting_pair_its_neighbours_contradict_is_not_corroborated() -> None:
    """The Pose2Sim lab on the subject path's cameras (2026-11-29, five markers): cam02-cam03's search puts cam03
    0.38 s from registration's offset, cam01-cam03's (not distinct) 0.23 s the other way, and the pairs with cam02
    agree with the given offsets: nothing shares cam02-cam03's evidence."""
    verdicts = [
        _verdict("cam01", "cam02", 0.0009, -0.0167, 15.5),
        _verdict("cam01", "cam03", 0.0004, -0.2333, 1.48),
        _verdict("cam01", "cam04", 0.0000, -0.0167, 29.4),
        _verdict("cam02", "cam03", -0.0005, 0.3833, 3.09),
        _verdict("cam02", "cam04", -0.0010, 0.0667, 17.2),
    ]
    assert [v.refutes for v in verdicts] == [False, False, False, True, False]
    assert not corroborated(verdicts[3], verdicts)


@pytest.mark.parametrize("first", [True, False], ids=["off-video-second", "off-video-first"])
def test_one_video_off_is_corroborated_by_its_other_pairs(first: bool) -> None:
    """cam3's given offset 0.5 s wrong: every pair with cam3 prefers the same correction, whichever side of the
    pair it stands on; with two videos the single pair's word stands."""
    offsets = {"cam1": 0.0, "cam2": 0.1, "cam3": -0.2}  # true
    given = {**offsets, "cam3": offsets["cam3"] + 0.5}
    names = ["cam3", "cam1", "cam2"] if first else ["cam1", "cam2", "cam3"]
    verdicts = [
        _verdict(a, b, given[a] - given[b], offsets[a] - offsets[b])
        for i, a in enumerate(names)
        for b in names[i + 1 :]
    ]
    refuting = [v for v in verdicts if v.refutes]
    assert len(refuting) == 2 and all("cam3" in (v.v, v.u) for v in refuting)
    assert all(corroborated(v, verdicts) for v in refuting)
    alone = [v for v in verdicts if {v.v, v.u} == {"cam1", "cam3"}]
    assert corroborated(alone[0], alone)
