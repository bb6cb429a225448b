"""The `solve` stage: cameras.json + tracks.csv -> points3d.csv, sequencing.json, report.json, recording.rrd.

`solve` works on loaded objects (or paths) and returns a `Reconstruction`: the self-expressive solve (the paper),
video clocks and trajectory refinement on them (reconstruct/temporal.py) and the trust measures of the solve
(reconstruct/trust.py). `Reconstruction.write` writes the files; `run` is the file-level stage the CLI calls
(`dynrecon solve`): solve + write.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import os
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.atomic import atomic_write_text, remove_temp_files, require_writable
from dynrecon.beside import beside
from dynrecon.errors import InputError
from dynrecon.jsonvalues import finite_or_none
from reconstruct.camera_order import check_camera_order
from reconstruct.clocks.model import ClockModel
from reconstruct.clocks.overlap import lonely_videos
from reconstruct.clocks.rates import RateCheck, check_given_rates
from reconstruct.clocks.registered import check_registered_clocks
from reconstruct.fit import check_fit
from reconstruct.heldout import heldout_px, holds_out
from reconstruct.inputs import build_problem_checked
from reconstruct.outputs.points import FramePoints, Sequencing, write_points, write_sequencing
from reconstruct.outputs.recording_options import RecordingOptions
from reconstruct.registered_offsets import PATH as REGISTERED_PATH
from reconstruct.registered_offsets import prefer_registered_offsets, registered_clocks
from reconstruct.solver.alternation import SolveResult, SolverOptions
from reconstruct.solver.alternation import solve as solve_problem
from reconstruct.solver.problem import Problem, reconstructable_points
from reconstruct.solver.unseen_frames import take_frames
from reconstruct.temporal import Refinement, Temporal, TemporalOptions, recover_and_refine
from reconstruct.time_checks import Check, TimePath
from reconstruct.tracks_path import (
    FEW_POINTS,
    Clocked,
    TracksAttempt,
    clocks_seed,
    solve_on_given_clocks,
    solve_on_tracks,
    solve_without_unclocked,
)
from reconstruct.tracks_path import applies as tracks_path_applies
from reconstruct.tracks_path import refereed as tracks_path_refereed
from reconstruct.trajectory import predicted_px
from reconstruct.trust import Trust, TrustOptions, TrustPreset, preset_options
from reconstruct.trust import trust_measures as measure_trust
from sfm.cameras import CameraSet, read_cameras
from sfm.people import check_people_mapped, people_maps, renumber_people
from sfm.report_read import unposed_videos
from tracking.tracks import Tracks, matched_to_videos, read_tracks

log = logging.getLogger(__name__)

# Coefficients below this are numerical dust of the exact W-step, not neighbours.
SEQUENCING_THRESHOLD = 1e-6


@dataclasses.dataclass(kw_only=True)
class SolveOptions:
    """Options of `solve` and `Reconstruction.write` (`dynrecon solve`).

    solver: the self-expressive solve (`SolverOptions`: weights, ray constraint, iterations, W-step, long captures).
    temporal: clock recovery and trajectory refinement after it (`TemporalOptions`).
    trust: the flag rule of points3d.csv (`TrustOptions`); default the sensitive preset, which flags more points
    and misses fewer large errors than the balanced one (`reconstruct.trust.preset_options`).
    recording: how to draw recording.rrd (`RecordingOptions`); None writes no recording.
    skeleton: pairs of point names drawn as bones in the recording (pairs naming unknown points are left out).
    videos: solve only these videos of the cameras file (and their tracks); empty: all of them.
    """

    solver: SolverOptions = dataclasses.field(default_factory=SolverOptions)
    temporal: TemporalOptions = dataclasses.field(default_factory=TemporalOptions)
    trust: TrustOptions = dataclasses.field(default_factory=lambda: preset_options(TrustPreset.SENSITIVE))
    recording: RecordingOptions | None = dataclasses.field(default_factory=RecordingOptions)
    skeleton: tuple[tuple[str, str], ...] = ()
    videos: tuple[str, ...] = ()


@dataclasses.dataclass(kw_only=True)
class Reconstruction:
    """What `solve` found. `points` and `sequencing` are the contents of points3d.csv and sequencing.json, `report`
    that of report.json; `seed` is the paper's self-expressive solve, `temporal` the video clocks
    (`temporal.clocks`) and the trajectories refined on them, `trust` the per-point trust measures and flag."""

    points: FramePoints
    sequencing: Sequencing
    temporal: Temporal
    trust: Trust
    report: dict[str, Any]
    seed: SolveResult
    problem: Problem
    cameras: CameraSet
    tracks: Tracks
    options: SolveOptions
    started: float = dataclasses.field(repr=False)  # perf_counter() when the solve began, for report timings

    def write(self, out_dir: str | Path) -> Path:
        """Write points3d.csv, sequencing.json, recording.rrd (unless `options.recording` is None) and report.json
        into `out_dir`; returns the path of points3d.csv."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        timings = self.report["timings"]
        # The recording (mostly importing rerun) is written beside the CSV (dynrecon/beside.py), under a temporary
        # name that is published only when both succeeded: a failed write leaves no recording of this solve.
        pending = out_dir / f".recording.rrd.{os.getpid()}.pending"
        recording = beside(self._timed_recording, pending) if self.options.recording else None
        try:
            with recording or nullcontext():
                t0 = time.perf_counter()
                points_path = write_points(out_dir / "points3d.csv", self.points)
                write_sequencing(out_dir / "sequencing.json", self.sequencing)
                timings["writing"] = time.perf_counter() - t0
                if recording is not None:
                    timings["recording"] = recording.result()
                    os.replace(pending, out_dir / "recording.rrd")
        finally:
            pending.unlink(missing_ok=True)
            # a writer stopped early, or killed inside native code, may leave its own temporary file of `pending`
            remove_temp_files(pending)
        timings["stage_total"] = time.perf_counter() - self.started
        atomic_write_text(out_dir / "report.json", json.dumps(self.report, indent=1, default=_json_default) + "\n")
        log.info("wrote %s", out_dir)
        return points_path

    def _timed_recording(self, path: Path) -> float:
        t0 = time.perf_counter()
        self.write_recording(path, self.options.recording)
        return time.perf_counter() - t0

    def write_recording(self, path: str | Path, options: RecordingOptions | None = None) -> Path:
        """The rerun recording (3D points, cameras, tracks, residual, skeleton) at `path`."""
        from reconstruct.outputs.recording import write_recording  # rerun is slow to import

        known = set(self.problem.point_names)
        bones = [bone for bone in self.options.skeleton if bone[0] in known and bone[1] in known]
        times = self.temporal.times
        return write_recording(
            path,
            cameras=self.cameras,
            points=self.points,
            tracks=self.tracks,
            residual=self.seed.residual,
            skeleton=bones or None,
            global_time=times if np.isfinite(times).any() else None,
            options=options,
        )


def solve(
    cameras: CameraSet | str | Path, tracks: Tracks | str | Path, options: SolveOptions | None = None
) -> Reconstruction:
    """Reconstruct the points of `tracks` (tracks.csv or its `Tracks`) seen by `cameras` (cameras.json or its
    `CameraSet`): the self-expressive solve, then the video clocks and trajectory refinement, then trust.

    Raises InputError / NotEnoughDataError (dynrecon.errors) when the inputs do not fit or are too few."""
    options = options or SolveOptions()
    started = time.perf_counter()
    camera_set = cameras if isinstance(cameras, CameraSet) else read_cameras(cameras)
    every_video = [video.name for video in camera_set.videos]  # before --videos takes some
    track_set = tracks if isinstance(tracks, Tracks) else read_tracks(tracks)
    track_set = matched_to_videos(track_set, [video.name for video in camera_set.videos])
    if not isinstance(cameras, CameraSet):
        track_set = _without_unregistered(track_set, camera_set, Path(cameras))
    if options.videos:  # after the names are matched: `--videos` names the cameras file's videos
        camera_set, track_set = _only_videos(camera_set, track_set, options.videos, cameras)
    # people numbered per video, as registration matched them across videos (cameras.json `people`)
    check_people_mapped(camera_set, track_set)
    track_set = renumber_people(track_set, people_maps(camera_set))
    cameras_path = None if isinstance(cameras, CameraSet) else Path(cameras)
    problem, rejected = build_problem_checked(camera_set, track_set, cameras_path=cameras_path)
    started_rates = time.perf_counter()
    problem, options, rates = _with_given_rates(problem, options, camera_set)
    rates_seconds = time.perf_counter() - started_rates
    clock_options = options.temporal.clocks
    check_camera_order(problem, cameras_path, clock_options.fps, clock_options.track_search, every_video)
    unknown = sorted({n for bone in options.skeleton for n in bone} - set(problem.point_names))
    if unknown:  # a typo in the skeleton file: its bones are not drawn, which the recording alone would not say
        log.warning("skeleton: point(s) %s not in the tracks: their bones are not drawn", ", ".join(unknown))
    read_inputs = time.perf_counter() - started
    log.info(
        "solving %d frames of %d videos, %d points, %d observations",
        problem.num_frames,
        len(problem.video_names),
        problem.num_points,
        int(problem.observed.sum()),
    )
    problem, result, temporal = _solve_and_refine(problem, options, camera_set)
    result.timings["read_inputs"] = read_inputs - rates_seconds
    if rates is not None:
        result.timings["given_rates"] = rates_seconds
    # the split of clocks and refinement, where reconstruct/temporal.py reports one
    result.timings.update(temporal.report.get("timings", {}))
    registration_check = check_registered_clocks(camera_set, temporal.clocks)
    if options.temporal.refinement is Refinement.CLOCKS:
        t0 = time.perf_counter()
        temporal = prefer_registered_offsets(
            problem,
            camera_set,
            result,
            temporal,
            registration_check,
            options.temporal.refine,
            options.temporal.clocks.track_search,
        )
        if not result.stages and temporal.report.get("path") == REGISTERED_PATH:
            # the tracks path's W came from the clocks just replaced: the trust measures need the kept ones'
            result = clocks_seed(problem, result.points, temporal.points, temporal.times, result.timings)
        result.timings["registered_offsets"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # without a seed solve (the tracks path) the trust measures describe the refined points against the clocks' W;
    # so they do where registration's offsets replaced the seed's clocks: those points are not the seed's refined
    judged = result if result.stages else dataclasses.replace(result, points=temporal.points)
    if result.stages and temporal.report.get("path") == REGISTERED_PATH:
        judged = clocks_seed(problem, temporal.points, temporal.points, temporal.times, result.timings)
    trust = measure_trust(problem, judged, options.trust, temporal.times)
    result.timings["trust"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    inputs = {"cameras": _input_name(cameras, None), "tracks": _input_name(tracks, track_set.path)}
    report = build_report(problem, result, options, inputs, seed_solved=bool(result.stages))
    report["clocks"] = {key: value for key, value in temporal.clocks.to_json().items() if key != "frames"}
    report["clocks"]["registration_check"] = registration_check  # of the solve's own clocks
    report["clocks"]["given_rates"] = rates.to_json() if rates is not None else None
    if rates is not None and rates.model is ClockModel.AFFINE:  # logged as a warning: the report keeps it too
        report["clocks"]["warnings"] = [*report["clocks"].get("warnings", []), f"clock model: {rates.reason}"]
    lonely = lonely_videos(temporal.clocks) if temporal.report.get("path") != TimePath.SEED.value else []
    for warning in lonely:
        log.warning("%s", warning)
    report["clocks"]["warnings"] = [*report["clocks"].get("warnings", []), *lonely]
    _say_unused_clocks(report["clocks"], temporal.report)
    report["temporal"] = temporal.report
    report["trust"] = trust.summary()
    refined = temporal.report.get("path") not in (None, "seed")
    predicted = predicted_px(temporal.trajectories) if temporal.trajectories is not None else None
    report["fit"] = check_fit(
        problem, temporal.points, trust, refined, predicted, lambda: _heldout_px(problem, temporal, options)
    )
    report["rejected_observations"] = rejected.to_json()
    points, frames_sequencing = frame_points(problem, result, temporal, trust), sequencing(problem, result, temporal)
    report["timings"]["outputs"] = time.perf_counter() - t0
    return Reconstruction(
        points=points,
        sequencing=frames_sequencing,
        temporal=temporal,
        trust=trust,
        report=report,
        seed=result,
        problem=problem,
        cameras=camera_set,
        tracks=track_set,
        options=options,
        started=started,
    )


def _with_given_rates(
    problem: Problem, options: SolveOptions, cameras: CameraSet
) -> tuple[Problem, SolveOptions, RateCheck | None]:
    """The videos whose frames are at a given rate (cameras.json `fps` and no times: `register --fps`'s and
    `import-calibration --fps`'s names; or `ClockOptions.fps`): `problem` with their times at frame / fps (the seed
    solve's windows and the trust flag's jumps read them), `options` whose clocks take them as given rates, and
    with `--clock-model auto` the model the tracks choose for those rates (`reconstruct.clocks.rates`)."""
    given = dict(options.temporal.clocks.fps)
    for video in cameras.videos:  # as `own_times`: under two decoder times, a video has none
        if video.fps and video.name not in given and sum(f.time is not None for f in video.frames) < 2:
            given[video.name] = float(video.fps)
    timed = {
        name
        for v, name in enumerate(problem.video_names)
        if np.isfinite(problem.times[problem.video_index == v]).sum() >= 2
    }
    # a rate given for a video with decoder times would replace them (`own_times`): its decoder measured them
    given = {
        name: rate for name, rate in given.items() if name in problem.video_names and name not in timed and rate > 0
    }
    if not given:
        return problem, options, None
    times = problem.times.copy()
    for v, name in enumerate(problem.video_names):
        if name in given:
            rows = problem.video_index == v
            times[rows] = problem.frames[rows] / given[name]
    problem = dataclasses.replace(problem, times=times)
    temporal = dataclasses.replace(options.temporal, clocks=dataclasses.replace(options.temporal.clocks, fps=given))
    check = check_given_rates(problem, temporal.clocks) if temporal.clock_model is None else None
    if check is not None:
        (log.warning if check.model is ClockModel.AFFINE else log.info)("clock model: %s", check.reason)
        temporal = dataclasses.replace(temporal, clock_model=check.model)
    return problem, dataclasses.replace(options, temporal=temporal), check


def _heldout_px(problem: Problem, temporal: Temporal, options: SolveOptions) -> tuple[float, dict[str, float]] | None:
    """The median error of each video's rays predicted by the trajectories the other videos give, at the solve's
    times (on the frames that have one), and per video; None where fewer than three videos see those frames."""
    timed = np.isfinite(temporal.times)
    sub = take_frames(problem, timed)
    if not timed.any() or not holds_out(sub):
        return None
    held = heldout_px(sub, temporal.times[timed], options.temporal.refine)
    per_video = {
        name: float(px) for name, px in zip(sub.video_names, held.per_video_px, strict=True) if np.isfinite(px)
    }
    return held.median_px, per_video


def _say_unused_clocks(clocks: dict[str, Any], temporal: dict[str, Any]) -> None:
    """report.json `clocks.used`: false where the points are the seed solve's, with why in `clocks.warnings` (a
    failed check, or the refinement turned off), so that the clocks' offsets are not read as a result."""
    clocks["used"] = temporal.get("path") != TimePath.SEED.value
    if clocks["used"]:
        return
    failed = next((c for c in temporal.get("checks", []) if not c.get("passed", True)), None)
    if failed is not None:
        why = f"the clocks' {Check.from_json(failed).sentence()}"
    elif temporal.get("refinement") == Refinement.NONE.value:
        why = "the refinement was off (--refinement none)"
    else:
        why = str(temporal.get("reason") or "the solve kept its seed")
    clocks["warnings"] = [
        *clocks.get("warnings", []),
        f"not used: {why}, and the points are the self-expressive solve's; the offsets are the clock estimate's "
        "best guess, not a result the points rest on",
    ]


def _without_unregistered(tracks: Tracks, cameras: CameraSet, cameras_path: Path) -> Tracks:
    """`tracks` without the videos that the registration beside `cameras_path` could not pose (not in cameras.json,
    listed unposed in register_report.json), with a warning each: the tracks register read name them too."""
    known = {video.name for video in cameras.videos}
    unposed = unposed_videos(cameras_path)
    left = sorted(name for name in set(tracks.video_names()) - known if name in unposed)
    for name in left:
        log.warning(
            "%s: video %r is left out: registration did not pose it (%s: %s)",
            tracks.path or "tracks",
            name,
            cameras_path.parent / "register_report.json",
            unposed[name],
        )
    return tracks.of_videos(set(tracks.video_names()) - set(left)) if left else tracks


def _only_videos(
    cameras: CameraSet, tracks: Tracks, names: tuple[str, ...], source: object
) -> tuple[CameraSet, Tracks]:
    """The cameras and tracks of the videos `names` (`SolveOptions.videos`)."""
    known = [video.name for video in cameras.videos]
    unknown = [name for name in names if name not in known]  # first: a typo is the likelier mistake
    if unknown:
        raise InputError(
            source if isinstance(source, (str, Path)) else None,
            f"--videos names {', '.join(unknown)}, not in the cameras file",
            fix=f"its videos: {', '.join(known)}",
        )
    if len(set(names)) < 2:
        raise InputError(None, f"--videos names {len(set(names))} video: a solve needs at least two")
    chosen = dataclasses.replace(cameras, videos=[video for video in cameras.videos if video.name in names])
    return chosen, tracks.of_videos(names)


def _solve_and_refine(
    problem: Problem, options: SolveOptions, cameras: CameraSet
) -> tuple[Problem, SolveResult, Temporal]:
    """The tracks path (for few points, or refereed beyond) when it passes its checks (reconstruct/tracks_path.py),
    else, for at most FEW_POINTS points, cameras.json's clock offsets when they fit, else the tracks path on the
    videos it clocked, the others left out (the seed solve is singular there), else the seed solve and the clocks
    and refinement after it; the report says which and why. The problem returned is the one solved."""
    temporal_options = options.temporal
    tried: dict[str, Any] | None = None
    attempt_seconds = 0.0
    few = tracks_path_applies(problem, temporal_options.tracks_path_max_points)
    refereed = tracks_path_refereed(problem, temporal_options)
    if temporal_options.refinement is Refinement.CLOCKS and (few or refereed):
        t0 = time.perf_counter()
        attempt = solve_on_tracks(problem, temporal_options, referee=options.solver if refereed else None)
        if attempt.temporal is not None and attempt.seed is not None:
            attempt.seed.timings["clocks_and_refinement"] = time.perf_counter() - t0
            return problem, attempt.seed, attempt.temporal
        tried, attempt_seconds = attempt.report, time.perf_counter() - t0
        given = _on_given_offsets(problem, cameras, attempt, temporal_options)
        if given is not None:
            seed, temporal = given
            seed.timings["tracks_path_attempt"] = attempt_seconds
            seed.timings["clocks_and_refinement"] = time.perf_counter() - t0
            return problem, seed, temporal
        clocked = _without_unclocked(problem, attempt, temporal_options)
        if clocked is not None:
            clocked.seed.timings["tracks_path_attempt"] = attempt_seconds
            clocked.seed.timings["clocks_and_refinement"] = time.perf_counter() - t0
            return clocked.problem, clocked.seed, clocked.temporal
    if tried is not None:
        log.warning("solving with the seed solve%s", _seed_cost_hint(problem, cameras))
    result = solve_problem(problem, options.solver)
    t0 = time.perf_counter()
    temporal = recover_and_refine(problem, result, temporal_options)
    result.timings["clocks_and_refinement"] = time.perf_counter() - t0
    if tried is not None:
        # the tracks' clocks failed a check: the seed solve's answer, with the tracks' attempt
        temporal.report["tracks_path"] = _tried(tried)
        if "referee" in tried:
            result.timings["referee"] = tried["referee"]["seconds"]
        result.timings["tracks_path_attempt"] = attempt_seconds  # what the failed attempt cost, referee included
        temporal.report["reason"] = f"tracks path failed its check {tried['failed']!r}: the seed solve was run"
    return problem, result, temporal


def _without_unclocked(problem: Problem, attempt: TracksAttempt, options: TemporalOptions) -> Clocked | None:
    """Few points whose tracks clock some videos only: the tracks path on those (`solve_without_unclocked`), said in
    a warning and report.json `temporal.left_out`; None where it does not apply or fails."""
    if int(reconstructable_points(problem).sum()) > FEW_POINTS:
        return None
    clocked = solve_without_unclocked(problem, attempt, options)
    if clocked is None:
        return None
    left = ", ".join(clocked.left_out)
    log.warning(
        "the tracks give no clock for video(s) %s (check %r failed): left out of the solve (no rows in "
        "points3d.csv); the other %d videos are solved on their clocks from the tracks, without the seed solve, "
        "which is singular for %d point(s). To keep them: their clock offsets in cameras.json (`register --offsets "
        "NAME=S`, or --synchronized for a triggered rig), or tracks that overlap the others' in time",
        left,
        attempt.report["failed"],
        len(clocked.problem.video_names),
        int(reconstructable_points(problem).sum()),
    )
    report = clocked.temporal.report
    report["tracks_path"] = _tried(attempt.report)
    report["left_out"] = clocked.left_out
    report["reason"] = (
        f"tracks path failed its check {attempt.report['failed']!r}; with {FEW_POINTS} or fewer points the seed "
        f"solve is singular: the tracks path on the videos it clocked, {left} left out"
    )
    return clocked


def _on_given_offsets(
    problem: Problem, cameras: CameraSet, attempt: TracksAttempt, options: TemporalOptions
) -> tuple[SolveResult, Temporal] | None:
    """Few points whose tracks did not single out their clocks: the trajectories on cameras.json's clock offsets
    (registration's, or declared synchronized), held to the tracks path's fit check, instead of the seed solve,
    whose W-step is singular for so few points (docs/measurements.md); None where they are missing or fail."""
    if attempt.clocks is None or int(reconstructable_points(problem).sum()) > FEW_POINTS:
        return None
    clocks = registered_clocks(problem, cameras, attempt.clocks)
    if clocks is None:
        return None
    given = solve_on_given_clocks(problem, clocks, options, REGISTERED_PATH)
    tried = _tried(attempt.report)
    if given.temporal is None or given.seed is None:
        attempt.report["registered_offsets"] = {"checks": given.report["checks"], "failed": given.report["failed"]}
        return None
    fit = given.temporal.report["checks"][-1]
    log.warning(
        "the tracks did not single out the clocks (check %r failed): the trajectories are fitted on cameras.json's "
        "clock offsets, which no pair of videos refutes and which fit them (%s %.3g, limit %.3g)",
        attempt.report["failed"],
        fit["meaning"],
        fit["value"],
        fit["limit"],
    )
    given.temporal.report["tracks_path"] = tried
    given.temporal.report["reason"] = (
        f"tracks path failed its check {attempt.report['failed']!r}; with {FEW_POINTS} or fewer points the seed "
        "solve is singular: fitted on cameras.json's clock offsets, which passed the tracks path's fit check"
    )
    return given.seed, given.temporal


def _seed_cost_hint(problem: Problem, cameras: CameraSet | None = None) -> str:
    """What the seed solve costs where its W-step is singular (few points), and how to avoid it: clock offsets,
    unless cameras.json gave them (they were tried and refuted: the cameras or the tracks are then in question)."""
    count = int(reconstructable_points(problem).sum())
    if count > FEW_POINTS:
        return ""
    cost = f" (with {count} point(s) its W-step is singular and {problem.num_frames} frames may take many minutes; "
    videos = [] if cameras is None else [v for v in cameras.videos if v.name in problem.video_names]
    if videos and all(v.clock_offset is not None for v in videos):
        said = "declared" if all(v.clock_declared for v in videos) else "registered"
        return (
            f"{cost}cameras.json's {said} clock offsets did not fit the tracks (above): where they are right, the "
            "cameras do not fit these tracks: check the calibration, and that each video has its own camera)"
        )
    counts = np.bincount(problem.video_index, minlength=len(problem.video_names))
    alike = (
        f"; the {len(counts)} videos have {counts[0]} posed frames each: a triggered rig?"
        if len(counts) > 1 and (counts == counts[0]).all()
        else ""
    )
    return (
        f"{cost}clock offsets in cameras.json avoid it: register's, or declared for videos on one clock with "
        f"--synchronized of `run`, `register` or `import-calibration`{alike})"
    )


def _tried(report: dict[str, Any]) -> dict[str, Any]:
    """report.json `temporal.tracks_path`: the failed attempt's checks (and referee, offsets tried after it)."""
    keys = ("checks", "failed", "referee", "registered_offsets", "without_unclocked")
    return {key: report[key] for key in keys if key in report}


def run(
    cameras_path: str | Path, tracks_path: str | Path, out_dir: str | Path, options: SolveOptions | None = None
) -> Path:
    """The file-level stage: `solve` cameras_path + tracks_path and write the outputs into `out_dir`; returns the
    path of points3d.csv."""
    require_writable(out_dir)  # before minutes of solving, not after
    return solve(cameras_path, tracks_path, options).write(out_dir)


def _input_name(given: object, fallback: Path | None) -> str | None:
    """How report.json names an input: the path given, else the file the object was read from (None: in memory)."""
    if isinstance(given, (str, Path)):
        return str(given)
    return None if fallback is None else str(fallback)


def frame_points(
    problem: Problem, result: SolveResult, temporal: Temporal | None = None, trust: Trust | None = None
) -> FramePoints:
    """The points3d.csv content: refined points when `temporal` refined them, with the global `time` of each frame
    and the trust columns as extra columns."""
    extra: dict[str, np.ndarray] = {}
    if temporal is not None:
        extra["time"] = np.repeat(temporal.times[:, None], problem.num_points, axis=1)
    if trust is not None:
        extra.update(trust.columns())
    xyz = temporal.points if temporal is not None else result.points
    return FramePoints(
        videos=problem.frame_videos,
        frames=problem.frames,
        point_names=problem.point_names,
        xyz=xyz,
        observed=problem.observed,
        extra=extra,
    )


def sequencing(problem: Problem, result: SolveResult, temporal: Temporal | None = None) -> Sequencing:
    neighbours, weights = [], []
    for f in range(problem.num_frames):
        j, w = result.W.column(f, SEQUENCING_THRESHOLD)
        order = np.argsort(-w)
        neighbours.append(j[order])
        weights.append(w[order])
    extra = {"clocks": temporal.clocks.to_json()} if temporal is not None else {}
    return Sequencing(
        videos=problem.frame_videos, frames=problem.frames, neighbours=neighbours, weights=weights, extra=extra
    )


def build_report(
    problem: Problem,
    result: SolveResult,
    options: SolveOptions,
    inputs: dict[str, str | None],
    *,
    seed_solved: bool = True,
) -> dict[str, Any]:
    """report.json; without a seed solve (the tracks path) its initialization is None."""
    unreconstructable = [n for n, ok in zip(problem.point_names, result.reconstructable, strict=True) if not ok]
    return {
        "inputs": inputs,
        "parameters": dataclasses.asdict(options.solver, dict_factory=_options_dict),
        "temporal_parameters": dataclasses.asdict(options.temporal, dict_factory=_options_dict),
        "size": {
            "frames": problem.num_frames,
            "videos": len(problem.video_names),
            "points": problem.num_points,
            "observations": int(problem.observed.sum()),
        },
        "normalization": {"offset": result.normalization.offset.tolist(), "scale": result.normalization.scale},
        "unreconstructable_points": unreconstructable,
        "initialization": {"frames_without_partner": int(np.sum(result.init.partner < 0))} if seed_solved else None,
        "stages": [dataclasses.asdict(stage) for stage in result.stages],
        "timings": dict(result.timings),
        "residual": {
            "unit": "input units, RMS over points of S_f - sum_j W_jf S_j",
            "median": float(np.nanmedian(result.residual)),
            "per_frame": [
                {"video": v, "frame": int(f), "residual": finite_or_none(r)}  # null: a frame that observes nothing
                for v, f, r in zip(problem.frame_videos, problem.frames, result.residual, strict=True)
            ],
        }
        if np.isfinite(result.residual).any()
        else None,
    }


def _options_dict(items: list[tuple[str, Any]]) -> dict[str, Any]:
    return {key: _json_default(value) for key, value in items}


def _json_default(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value
