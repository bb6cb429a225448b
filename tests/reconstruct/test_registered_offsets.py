"""Registration's clock offsets as a second hypothesis (reconstruct/registered_offsets.py): kept only where the
solve's clocks disagree with them and each video's rays are predicted clearly better from the other videos'."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from synthetic_motion import simulated_phones, truth_array

from reconstruct.clocks.model import TimeSource
from reconstruct.clocks.registered import check_registered_clocks
from reconstruct.heldout import holds_out
from reconstruct.outputs.points import read_points
from reconstruct.registered_offsets import PATH, prefer_registered_offsets
from reconstruct.stage import Reconstruction, SolveOptions, solve
from reconstruct.temporal import Temporal, TemporalOptions
from reconstruct.tracks_path import time_w
from reconstruct.trajectory import refine
from sfm.cameras import CameraSet, read_cameras


@pytest.fixture(scope="module")
def phones(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_phones(tmp_path_factory.mktemp("phones"))


def _cameras(sim: Path, shift: dict[str, float]) -> CameraSet:
    clocks = json.loads((sim / "clocks_truth.json").read_text())
    cameras = read_cameras(sim / "cameras.json")
    for video in cameras.videos:
        truth = next(v for v in clocks["videos"] if v["name"] == video.name)
        video.clock_offset = truth["offset_s"] + shift.get(video.name, 0.0) + 5.0  # any common origin
    return cameras


def _error_mm(points: np.ndarray, truth: np.ndarray) -> float:
    return float(np.nanmedian(np.linalg.norm(points - truth, axis=-1)))


def _right(phones: Path) -> tuple[CameraSet, SolveOptions, Reconstruction, np.ndarray]:
    """Cameras with the true registered offsets, the solve's options, its solution and the true points."""
    cameras = _cameras(phones, {})
    options = SolveOptions(recording=None)
    good = solve(cameras, phones / "tracks.csv", options)
    return cameras, options, good, truth_array(good.problem, read_points(phones / "truth.csv"))


def test_right_offsets_replace_clocks_that_went_wrong(phones: Path) -> None:
    cameras, options, good, truth = _right(phones)
    problem = good.problem
    # The solve's clocks with one video half a second off (a periodic motion, a wrong track search), not polished.
    wrong_clocks = copy.deepcopy(good.temporal.clocks)
    moved = problem.video_index == problem.video_names.index("cam2")
    wrong_clocks.global_time[moved] += 0.5
    wrong_clocks.video("cam2").offset += 0.5
    fitted = refine(problem, good.seed.points, wrong_clocks.global_time, options.temporal.refine)  # no polish
    wrong = Temporal(
        clocks=wrong_clocks, points=fitted.points, times=wrong_clocks.global_time.copy(), refined=True, report={}
    )
    check = check_registered_clocks(cameras, wrong.clocks)
    assert check is not None and not check["agree"]

    chosen = prefer_registered_offsets(problem, cameras, good.seed, wrong, check, options.temporal.refine)

    assert chosen.report["path"] == PATH and chosen.report[PATH]["kept"] == "registered"
    entry = chosen.report[PATH]
    assert entry["criterion"] == "heldout_px"
    assert entry["heldout_px"]["registered"] < 0.8 * entry["heldout_px"]["solve"]
    # the moved video is the one its held-out rays single out
    per_video = entry["heldout_per_video_px"]
    assert max(per_video, key=lambda name: per_video[name]["solve"] / per_video[name]["registered"]) == "cam2"
    assert _error_mm(chosen.points, truth) < 0.5 * _error_mm(wrong.points, truth)
    assert _error_mm(chosen.points, truth) < 2 * _error_mm(good.temporal.points, truth) + 1.0


def test_where_some_frame_has_no_time_the_residual_decides(phones: Path) -> None:
    """No held-out fit of an answer with untimed frames: the in-sample residual compares them, as before."""
    cameras, options, good, truth = _right(phones)
    problem = good.problem
    wrong_clocks = copy.deepcopy(good.temporal.clocks)
    wrong_clocks.global_time[problem.video_index == problem.video_names.index("cam2")] += 0.5
    wrong_clocks.video("cam2").offset += 0.5
    fitted = refine(problem, good.seed.points, wrong_clocks.global_time, options.temporal.refine)
    times = wrong_clocks.global_time.copy()
    times[np.flatnonzero(problem.video_index == 0)[:3]] = np.nan
    wrong = Temporal(clocks=wrong_clocks, points=fitted.points, times=times, refined=True, report={})

    chosen = prefer_registered_offsets(
        problem, cameras, good.seed, wrong, check_registered_clocks(cameras, wrong_clocks), options.temporal.refine
    )

    entry = chosen.report[PATH]
    assert entry["criterion"] == "residual_px" and "heldout_px" not in entry
    assert entry["kept"] == "registered" and _error_mm(chosen.points, truth) < _error_mm(wrong.points, truth)


def test_with_two_videos_the_residual_decides(phones: Path) -> None:
    """One video left out leaves one, which places no point in depth: no held-out fit, the residual compares."""
    cameras, options, good, truth = _right(phones)
    uv = good.problem.uv.copy()
    uv[good.problem.video_index == good.problem.video_names.index("cam1")] = np.nan
    problem = dataclasses.replace(good.problem, uv=uv)
    assert not holds_out(problem) and holds_out(good.problem)
    wrong_clocks = copy.deepcopy(good.temporal.clocks)
    wrong_clocks.global_time[problem.video_index == problem.video_names.index("cam2")] += 0.5
    wrong_clocks.video("cam2").offset += 0.5
    fitted = refine(problem, good.seed.points, wrong_clocks.global_time, options.temporal.refine)
    wrong = Temporal(
        clocks=wrong_clocks, points=fitted.points, times=wrong_clocks.global_time.copy(), refined=True, report={}
    )

    chosen = prefer_registered_offsets(
        problem, cameras, good.seed, wrong, check_registered_clocks(cameras, wrong_clocks), options.temporal.refine
    )

    entry = chosen.report[PATH]
    assert entry["criterion"] == "residual_px" and "heldout_px" not in entry and entry["kept"] == "registered"
    seen = problem.observed
    assert _error_mm(chosen.points[seen], truth[seen]) < _error_mm(wrong.points[seen], truth[seen])


def test_a_wrong_registered_offset_leaves_the_solve_as_it_was(phones: Path) -> None:
    options = SolveOptions(recording=None)
    plain = solve(read_cameras(phones / "cameras.json"), phones / "tracks.csv", options)
    checked = solve(_cameras(phones, {"cam2": 0.5}), phones / "tracks.csv", options)

    assert not checked.report["clocks"]["registration_check"]["agree"]
    entry = checked.temporal.report[PATH]
    assert entry["tried"] and entry["kept"] == "solve"
    # refuted before any refinement: the pairs with cam2 clearly prefer an offset about 0.5 s from it
    assert entry["criterion"] == "given_offsets" and not entry["checks"][0]["passed"]
    refuting = [pair for pair in entry["given_offsets"] if pair["refutes"]]
    assert refuting and all("cam2" in pair["videos"] for pair in refuting)
    assert checked.temporal.report["path"] == plain.temporal.report["path"]
    np.testing.assert_array_equal(checked.temporal.points, plain.temporal.points)


def test_offsets_that_agree_are_not_tried(phones: Path) -> None:
    checked = solve(_cameras(phones, {}), phones / "tracks.csv", SolveOptions(recording=None))
    assert checked.report["clocks"]["registration_check"]["agree"]
    assert PATH not in checked.temporal.report


def test_declared_offsets_that_agree_are_used(phones: Path) -> None:
    """Offsets the user declared (--synchronized, --offsets) are exact where the declaration is true: where the
    solve's clocks agree with them and predict no better, the trajectories are refined on them (a real triggered bat
    rig: one camera's recovered clock was 0.36 frame off, within the agreement's tolerance, and kept before)."""
    cameras = _cameras(phones, {})
    for video in cameras.videos:
        video.clock_declared = True
    estimated = solve(_cameras(phones, {}), phones / "tracks.csv", SolveOptions(recording=None))
    declared = solve(cameras, phones / "tracks.csv", SolveOptions(recording=None))
    assert declared.report["clocks"]["registration_check"]["agree"]
    entry = declared.temporal.report[PATH]
    assert entry["declared"] and entry["kept"] == "registered" and entry["criterion"] == "heldout_px"
    assert (
        declared.temporal.report["path"] == PATH
        and "agree with the declared clock offsets" in (declared.temporal.report["reason"])
    )
    truth = json.loads((phones / "clocks_truth.json").read_text())
    true_offsets = {v["name"]: v["offset_s"] for v in truth["videos"]}
    reference = declared.temporal.clocks.reference
    for clock in declared.temporal.clocks.videos:  # exactly the declared offsets, in the clocks' gauge
        assert clock.offset == pytest.approx(true_offsets[clock.name] - true_offsets[reference], abs=1e-12)
    truth_points = truth_array(declared.problem, read_points(phones / "truth.csv"))
    assert _error_mm(declared.temporal.points, truth_points) <= _error_mm(estimated.temporal.points, truth_points)


def test_declared_offsets_that_predict_clearly_worse_leave_the_solve(
    phones: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import reconstruct.registered_offsets as module

    cameras = _cameras(phones, {})
    for video in cameras.videos:
        video.clock_declared = True
    # the solve's clocks predicting every video's rays at half the declared offsets' error
    monkeypatch.setattr(module, "_compared", lambda *args: (2.0, 1.0, "declared 2 px against the solve's 1 px"))
    checked = solve(cameras, phones / "tracks.csv", SolveOptions(recording=None))
    entry = checked.temporal.report[PATH]
    assert entry["declared"] and entry["kept"] == "solve"
    assert checked.temporal.report["path"] != PATH


def test_clocks_under_which_no_ray_is_predicted_lose_whatever_the_residual(
    phones: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Offsets that put every video apart in time (milliseconds typed for seconds) fit each video alone: a small
    residual, and no video's rays predictable from the others'. They lose to clocks that predict, whatever the
    residual (before: kept, on the Pose2Sim lab with points metres off; docs/refinement.md)."""
    import reconstruct.registered_offsets as module
    from reconstruct.heldout import HeldOut

    _, options, good, _ = _right(phones)
    apart = good.temporal.times + 100.0 * good.problem.video_index
    N = len(good.problem.video_names)

    def held(problem, times, options):  # type: ignore[no-untyped-def]
        if np.array_equal(times, apart):
            return HeldOut(per_video_px=np.full(N, np.nan), rays_px=np.zeros(0))
        return HeldOut(per_video_px=np.full(N, 3.0), rays_px=np.full(5, 3.0))

    monkeypatch.setattr(module, "heldout_px", held)
    entry: dict = {}
    residual = {"solve": 9.1, "registered": 2.2}
    theirs, mine, sentence = module._compared(
        good.problem, good.temporal, apart, options.temporal.refine, residual, entry
    )
    assert (theirs, mine) == (math.inf, 3.0) and "no shared time" in sentence
    assert entry["heldout_px"] == {"solve": 3.0, "registered": None}
    # the other way round: the solve's clocks are the ones that predict nothing
    theirs, mine, _ = module._compared(
        good.problem, good.temporal, good.temporal.times, options.temporal.refine, residual, entry
    )
    assert (theirs, mine) == (3.0, 3.0)


def test_a_cameras_file_with_every_video_apart_in_time_leaves_the_solve(phones: Path) -> None:
    """End to end: declared offsets 10 s apart per video are tried and not kept; the polish on them, where no point
    is refined, keeps its clocks instead of failing."""
    names = [video.name for video in read_cameras(phones / "cameras.json").videos]
    cameras = _cameras(phones, {name: 10.0 * i for i, name in enumerate(names)})
    for video in cameras.videos:
        video.clock_declared = True
    plain = solve(read_cameras(phones / "cameras.json"), phones / "tracks.csv", SolveOptions(recording=None))
    checked = solve(cameras, phones / "tracks.csv", SolveOptions(recording=None))
    entry = checked.temporal.report[PATH]
    assert entry["tried"] and entry["kept"] == "solve" and entry["heldout_px"]["registered"] is None
    assert checked.temporal.report["path"] == plain.temporal.report["path"]
    np.testing.assert_array_equal(checked.temporal.points, plain.temporal.points)


def test_kept_offsets_rebuild_the_tracks_paths_w(phones: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On the tracks path W comes from the clocks, so the trust measures need W from the clocks that were kept."""
    import reconstruct.stage as stage

    def shifted(problem, cameras, seed, temporal, check, options, search=None):  # type: ignore[no-untyped-def]
        times = temporal.times.copy()
        times[problem.video_index == 1] += 0.05
        report = {**temporal.report, "path": PATH}
        return Temporal(clocks=temporal.clocks, points=temporal.points, times=times, refined=True, report=report)

    monkeypatch.setattr(stage, "prefer_registered_offsets", shifted)
    options = SolveOptions(recording=None, temporal=TemporalOptions(tracks_path_max_points=1000))
    solved = solve(_cameras(phones, {}), phones / "tracks.csv", options)

    assert not solved.seed.stages and solved.temporal.report["path"] == PATH
    expected = time_w(solved.problem, solved.temporal.times).to_csc()
    assert abs(solved.seed.W.to_csc() - expected).max() == 0.0


def test_a_kept_seed_with_unidentified_clocks_takes_registrations_offsets(phones: Path) -> None:
    """The seed's points sit on their rays: no residual can beat them, so registration's offsets, the only clocks
    for a video the solve could not time, are held to the clock checks instead."""
    cameras, options, good, truth = _right(phones)
    problem = good.problem
    clocks = copy.deepcopy(good.temporal.clocks)
    clocks.video("cam2").identified = False
    seed_kept = Temporal(
        clocks=clocks, points=good.seed.points, times=clocks.global_time.copy(), refined=False, report={"path": "seed"}
    )

    chosen = prefer_registered_offsets(
        problem, cameras, good.seed, seed_kept, check_registered_clocks(cameras, clocks), options.temporal.refine
    )

    entry = chosen.report[PATH]
    assert chosen.report["path"] == PATH and entry["kept"] == "registered" and entry["criterion"] == "clock_fit"
    assert [c["name"] for c in entry["checks"]] == ["clock_fit"]  # decoder times: reported, not judged
    assert "cam2 unidentified" in chosen.report["reason"]
    assert _error_mm(chosen.points, truth) < _error_mm(good.seed.points, truth)


def test_without_decoder_times_a_wrong_registered_offset_leaves_the_seed(phones: Path) -> None:
    """Without decoder times the clock checks compare with free per-frame times: a registered offset half a second
    off fits its rays worse than they do, and the seed stays."""
    _, options, good, _ = _right(phones)
    wrong = _cameras(phones, {"cam2": 0.5})
    clocks = copy.deepcopy(good.temporal.clocks)
    clocks.video("cam2").identified = False
    for video in clocks.videos:
        video.time_source = TimeSource.FPS
    seed_kept = Temporal(
        clocks=clocks, points=good.seed.points, times=clocks.global_time.copy(), refined=False, report={"path": "seed"}
    )

    chosen = prefer_registered_offsets(
        good.problem, wrong, good.seed, seed_kept, check_registered_clocks(wrong, clocks), options.temporal.refine
    )

    entry = chosen.report[PATH]
    assert entry["kept"] == "solve" and not entry["checks"][0]["passed"]
    assert chosen is seed_kept and chosen.report["path"] == "seed"


def test_a_kept_seed_whose_clocks_registration_confirms_takes_them(phones: Path) -> None:
    """Every clock found, but the solve's own checks judged them too ambiguous and kept the seed: registration's
    offsets, found independently, agree with them, so the trajectories are refined on them (held to the clock
    checks). On Pose2Sim's two-participant trial this took the markers from 207 mm to 4.3 mm (docs/refinement.md)."""
    cameras, options, good, truth = _right(phones)
    clocks = copy.deepcopy(good.temporal.clocks)
    assert all(c.identified for c in clocks.videos)
    seed_kept = Temporal(
        clocks=clocks, points=good.seed.points, times=clocks.global_time.copy(), refined=False, report={"path": "seed"}
    )
    check = check_registered_clocks(cameras, clocks)
    assert check is not None and check["agree"]

    chosen = prefer_registered_offsets(good.problem, cameras, good.seed, seed_kept, check, options.temporal.refine)

    entry = chosen.report[PATH]
    assert chosen.report["path"] == PATH and entry["kept"] == "registered" and entry["criterion"] == "clock_fit"
    assert "registration's offsets, found independently, agree" in chosen.report["reason"]
    assert _error_mm(chosen.points, truth) < _error_mm(good.seed.points, truth)
    # refined on the clocks (not kept as the seed) the same check does not apply: nothing is tried
    refined = prefer_registered_offsets(good.problem, cameras, good.seed, good.temporal, check, options.temporal.refine)
    assert refined is good.temporal
