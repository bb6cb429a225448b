"""The `solve` stage: cameras.json + tracks.csv -> points3d.csv, sequencing.json, report.json, recording.rrd."""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.atomic import atomic_write_text
from reconstruct.points import FramePoints, Sequencing, write_points, write_sequencing
from reconstruct.problem import Problem, build_problem
from reconstruct.recording import write_recording
from reconstruct.solver import SolveResult, SolverOptions, solve
from sfm.cameras import read_cameras
from tracking.tracks import read_tracks

log = logging.getLogger(__name__)

# Coefficients below this are numerical dust of the exact W-step, not neighbours.
SEQUENCING_THRESHOLD = 1e-6


@dataclasses.dataclass(kw_only=True)
class SolveStageOptions:
    solver: SolverOptions = dataclasses.field(default_factory=SolverOptions)
    recording: bool = True
    skeleton: tuple[tuple[str, str], ...] = ()  # point pairs drawn as bones in the recording


def run(cameras_path: Path, tracks_path: Path, out_dir: Path, options: SolveStageOptions | None = None) -> Path:
    """Reconstruct and write the outputs into `out_dir`; returns the path of points3d.csv."""
    options = options or SolveStageOptions()
    started = time.perf_counter()
    cameras = read_cameras(cameras_path)
    tracks = read_tracks(tracks_path)
    problem = build_problem(cameras, tracks)
    log.info("solving %d frames of %d videos, %d points, %d observations", problem.num_frames,
             len(problem.video_names), problem.num_points, int(problem.observed.sum()))
    result = solve(problem, options.solver)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    points = frame_points(problem, result)
    points_path = write_points(out_dir / "points3d.csv", points)
    write_sequencing(out_dir / "sequencing.json", sequencing(problem, result))
    if options.recording:
        known = set(problem.point_names)
        bones = [bone for bone in options.skeleton if bone[0] in known and bone[1] in known]
        write_recording(out_dir / "recording.rrd", cameras=cameras, points=points, tracks=tracks,
                        residual=result.residual, skeleton=bones or None)
    report = build_report(problem, result, options, cameras_path, tracks_path)
    report["timings"]["stage_total"] = time.perf_counter() - started
    atomic_write_text(out_dir / "report.json", json.dumps(report, indent=1, default=_json_default) + "\n")
    log.info("wrote %s", out_dir)
    return points_path


def frame_points(problem: Problem, result: SolveResult) -> FramePoints:
    return FramePoints(videos=problem.frame_videos, frames=problem.frames, point_names=problem.point_names,
                       xyz=result.points, observed=problem.observed)


def sequencing(problem: Problem, result: SolveResult) -> Sequencing:
    neighbours, weights = [], []
    for f in range(problem.num_frames):
        j, w = result.W.column(f, SEQUENCING_THRESHOLD)
        order = np.argsort(-w)
        neighbours.append(j[order])
        weights.append(w[order])
    return Sequencing(videos=problem.frame_videos, frames=problem.frames, neighbours=neighbours, weights=weights)


def build_report(problem: Problem, result: SolveResult, options: SolveStageOptions, cameras_path: Path,
                 tracks_path: Path) -> dict[str, Any]:
    unreconstructable = [n for n, ok in zip(problem.point_names, result.reconstructable, strict=True) if not ok]
    return {
        "inputs": {"cameras": str(cameras_path), "tracks": str(tracks_path)},
        "parameters": dataclasses.asdict(options.solver, dict_factory=_options_dict),
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
