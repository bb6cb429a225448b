"""The `solve` stage: cameras.json + tracks.csv -> points3d.csv, sequencing.json, report.json, recording.rrd.

Self-expressive solve (the paper) -> video clocks and trajectory refinement on them (reconstruct/temporal.py) ->
trust measures of the solve (reconstruct/trust.py) -> files.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.atomic import atomic_write_text, require_writable
from reconstruct.clocks.registered import check_registered_clocks
from reconstruct.inputs import build_problem
from reconstruct.outputs.points import FramePoints, Sequencing, write_points, write_sequencing
from reconstruct.outputs.recording import write_recording
from reconstruct.solver.alternation import SolveResult, SolverOptions, solve
from reconstruct.solver.problem import Problem
from reconstruct.temporal import Temporal, TemporalOptions, recover_and_refine
from reconstruct.trust import Trust, TrustOptions, TrustPreset, preset_options
from reconstruct.trust import trust_measures as measure_trust
from sfm.cameras import read_cameras
from tracking.tracks import read_tracks

log = logging.getLogger(__name__)

# Coefficients below this are numerical dust of the exact W-step, not neighbours.
SEQUENCING_THRESHOLD = 1e-6


@dataclasses.dataclass(kw_only=True)
class SolveStageOptions:
    solver: SolverOptions = dataclasses.field(default_factory=SolverOptions)
    temporal: TemporalOptions = dataclasses.field(default_factory=TemporalOptions)
    # The sensitive operating point: on simulations it catches 45-89 % of the points with errors over 30 mm
    # (benchmarks/trust.py); the balanced one flags fewer points but misses more.
    trust: TrustOptions = dataclasses.field(default_factory=lambda: preset_options(TrustPreset.SENSITIVE))
    recording: bool = True
    skeleton: tuple[tuple[str, str], ...] = ()  # point pairs drawn as bones in the recording


def run(cameras_path: Path, tracks_path: Path, out_dir: Path, options: SolveStageOptions | None = None) -> Path:
    """Reconstruct and write the outputs into `out_dir`; returns the path of points3d.csv."""
    options = options or SolveStageOptions()
    started = time.perf_counter()
    require_writable(out_dir)  # before minutes of solving, not after
    cameras = read_cameras(cameras_path)
    tracks = read_tracks(tracks_path)
    problem = build_problem(cameras, tracks)
    log.info("solving %d frames of %d videos, %d points, %d observations", problem.num_frames,
             len(problem.video_names), problem.num_points, int(problem.observed.sum()))
    result = solve(problem, options.solver)
    t0 = time.perf_counter()
    temporal = recover_and_refine(problem, result, options.temporal)
    result.timings["clocks_and_refinement"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    trust = measure_trust(problem, result, options.trust)
    result.timings["trust"] = time.perf_counter() - t0
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    points = frame_points(problem, result, temporal, trust)
    points_path = write_points(out_dir / "points3d.csv", points)
    write_sequencing(out_dir / "sequencing.json", sequencing(problem, result, temporal))
    if options.recording:
        known = set(problem.point_names)
        bones = [bone for bone in options.skeleton if bone[0] in known and bone[1] in known]
        write_recording(out_dir / "recording.rrd", cameras=cameras, points=points, tracks=tracks,
                        residual=result.residual, skeleton=bones or None,
                        global_time=temporal.times if np.isfinite(temporal.times).any() else None)
    report = build_report(problem, result, options, cameras_path, tracks_path)
    report["clocks"] = {key: value for key, value in temporal.clocks.to_json().items() if key != "frames"}
    report["clocks"]["registration_check"] = check_registered_clocks(cameras, temporal.clocks)
    report["temporal"] = temporal.report
    report["trust"] = trust.summary()
    report["timings"]["stage_total"] = time.perf_counter() - started
    atomic_write_text(out_dir / "report.json", json.dumps(report, indent=1, default=_json_default) + "\n")
    log.info("wrote %s", out_dir)
    return points_path


def frame_points(problem: Problem, result: SolveResult, temporal: Temporal | None = None,
                 trust: Trust | None = None) -> FramePoints:
    """The points3d.csv content: refined points when `temporal` refined them, with the global `time` of each frame
    and the trust columns as extra columns."""
    extra: dict[str, np.ndarray] = {}
    if temporal is not None:
        extra["time"] = np.repeat(temporal.times[:, None], problem.num_points, axis=1)
    if trust is not None:
        extra.update(trust.columns())
    xyz = temporal.points if temporal is not None else result.points
    return FramePoints(videos=problem.frame_videos, frames=problem.frames, point_names=problem.point_names,
                       xyz=xyz, observed=problem.observed, extra=extra)


def sequencing(problem: Problem, result: SolveResult, temporal: Temporal | None = None) -> Sequencing:
    neighbours, weights = [], []
    for f in range(problem.num_frames):
        j, w = result.W.column(f, SEQUENCING_THRESHOLD)
        order = np.argsort(-w)
        neighbours.append(j[order])
        weights.append(w[order])
    extra = {"clocks": temporal.clocks.to_json()} if temporal is not None else {}
    return Sequencing(videos=problem.frame_videos, frames=problem.frames, neighbours=neighbours, weights=weights,
                      extra=extra)


def build_report(problem: Problem, result: SolveResult, options: SolveStageOptions, cameras_path: Path,
                 tracks_path: Path) -> dict[str, Any]:
    unreconstructable = [n for n, ok in zip(problem.point_names, result.reconstructable, strict=True) if not ok]
    return {
        "inputs": {"cameras": str(cameras_path), "tracks": str(tracks_path)},
        "parameters": dataclasses.asdict(options.solver, dict_factory=_options_dict),
        "temporal_parameters": dataclasses.asdict(options.temporal, dict_factory=_options_dict),
        "size": {"frames": problem.num_frames, "videos": len(problem.video_names), "points": problem.num_points,
                 "observations": int(problem.observed.sum())},
        "normalization": {"offset": result.normalization.offset.tolist(), "scale": result.normalization.scale},
        "unreconstructable_points": unreconstructable,
        "initialization": {"frames_without_partner": int(np.sum(result.init.partner < 0))},
        "stages": [dataclasses.asdict(stage) for stage in result.stages],
        "timings": dict(result.timings),
        "residual": {"unit": "input units, RMS over points of S_f - sum_j W_jf S_j",
                     "median": float(np.nanmedian(result.residual)),
                     "per_frame": [{"video": v, "frame": int(f), "residual": float(r)} for v, f, r in
                                   zip(problem.frame_videos, problem.frames, result.residual, strict=True)]},
    }


def _options_dict(items: list[tuple[str, Any]]) -> dict[str, Any]:
    return {key: _json_default(value) for key, value in items if key != "monitor"}


def _json_default(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value
