"""The tasks of one capture, as plain functions of small arguments: paths and options in, files written, a small
`TaskOutcome` returned. Any machine that sees the shared filesystem can run any of them.

    probe (per video) -> register (one task: calibration import; for SfM, `batch.register_tasks`: per-video plan,
                      |   extract and localize tasks around one map task, then register)
                      |                                                   -> solve (one task: merge the per-video
                      -> track (per video, with labels; beside register)  ->  tracks, subject, solve, record, export)

The stages are `dynrecon.pipeline.Stages`, the public stage API of `dynrecon run` (its hashes, skipping and
`pipeline.json`; a calibrated capture's `register` imports the calibration there too): the register task runs
`Stages.register`, the solve task `Stages.finish` with the merge of the per-video tracks files as its tracker. User
errors (`DynreconError`) become a failed outcome with a one-line reason; anything else raises, so that Dask retries
it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from batch.capture import Capture
from dynrecon.atomic import atomic_write_text
from dynrecon.errors import DynreconError
from dynrecon.pipeline import PipelineOptions, Stages, inputs_key
from sfm.stage import RegistrationError
from sfm.video import probe_video
from tracking.labels import read_labels
from tracking.stage import run as track_run
from tracking.tracks import Tracks, read_tracks, write_tracks

log = logging.getLogger(__name__)

BATCH_DIR = "batch"  # WS/batch/: the per-video tasks' files
PROBE_DIR = "probe"  # WS/batch/probe/<video>.json
TRACK_DIR = "track"  # WS/batch/track/<video>/labels.csv, tracks.csv, task.json
TASK_NAME = "task.json"
STAGES = ("probe", "plan", "extract", "map", "localize", "register", "track", "solve")  # in order; see docs/scaling.md


@dataclass(kw_only=True)
class CaptureJob:
    """What every task of a capture needs: the capture's files, its workspace and the pipeline's options."""

    capture: Capture
    workspace: Path
    options: PipelineOptions

    @property
    def name(self) -> str:
        return self.capture.name

    def stages(self) -> Stages:
        """The pipeline's stages on this capture's workspace."""
        return Stages(self.capture.videos, self.workspace, self.options)


@dataclass(kw_only=True)
class TaskOutcome:
    """What a task returns through the scheduler: a few numbers and strings, never arrays."""

    capture: str
    stage: str  # one of STAGES
    video: str | None = None  # per-video tasks
    status: str = "done"  # done, skipped (up to date), failed
    seconds: float = 0.0
    error: str | None = None  # one line, when failed
    registration_error: str | None = None  # register: the background SfM failed, the subject path will pose
    pipeline: dict[str, float | None] = field(default_factory=dict)  # pipeline stage -> seconds (None: skipped)

    @property
    def failed(self) -> bool:
        return self.status == "failed"


def job_for(capture: Capture, out: Path, base: PipelineOptions) -> CaptureJob:
    """The capture's job: workspace `out/<name>`, the pipeline's options with the capture's own inputs."""
    options = dataclasses.replace(
        base,
        labels=capture.labels,
        tracks=capture.tracks,
        skeleton=capture.skeleton or base.skeleton,
        calibration=capture.calibration or base.calibration,  # one rig calibration may serve every capture
    )
    return CaptureJob(capture=capture, workspace=(out / capture.name).resolve(), options=options)


def one_line(error: BaseException) -> str:
    """An exception as the one line batch.json and the screen show."""
    text = " ".join(str(error).split()) or "no message"
    return text if isinstance(error, DynreconError) else f"{type(error).__name__}: {text}"


def guarded(job: CaptureJob, stage: str, video: str | None, body: Callable[[TaskOutcome], None]) -> TaskOutcome:
    """Run `body` on a fresh outcome; a user error becomes a failed outcome (other errors raise: Dask retries)."""
    outcome = TaskOutcome(capture=job.name, stage=stage, video=video)
    started = time.perf_counter()
    try:
        body(outcome)
    except DynreconError as error:
        outcome.status, outcome.error = "failed", one_line(error)
        log.warning("%s: %s failed: %s", job.name, stage, outcome.error)
    outcome.seconds = time.perf_counter() - started
    return outcome


def first_failure(outcomes: list[TaskOutcome]) -> TaskOutcome | None:
    return next((o for o in outcomes if o.failed), None)


# ----------------------------------------------------------------------------------------------------------
# Tasks


def probe_task(job: CaptureJob, video: Path) -> TaskOutcome:
    """Decode one video once (frames, timestamps, size) into WS/batch/probe/<video>.json; an unreadable video fails
    its capture here, before any long stage. Skipped while the video's size and modification time are unchanged."""

    def body(outcome: TaskOutcome) -> None:
        stat = video.stat()
        path = job.workspace / BATCH_DIR / PROBE_DIR / f"{video.stem}.json"
        stamp = {"video": str(video), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
        if not job.options.force and _cached(path, stamp):
            outcome.status = "skipped"
            return
        info = probe_video(video)
        document = {
            **stamp,
            "name": info.name,
            "frames": info.num_frames,
            "fps": info.fps,
            "width": info.width,
            "height": info.height,
            "duration_s": float(info.times[-1]),
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(document, indent=1) + "\n")

    return guarded(job, "probe", video.stem, body)


def register_task(job: CaptureJob, probes: list[TaskOutcome]) -> TaskOutcome:
    """The pipeline's `register` stage (SfM, or the calibration import): one task per capture."""
    failed = first_failure(probes)
    if failed is not None:
        return failed

    def body(outcome: TaskOutcome) -> None:
        stages = job.stages()
        background_failed = stages.register()
        outcome.registration_error = str(background_failed) if background_failed is not None else None
        note_stages(outcome, stages)

    return guarded(job, "register", None, body)


def track_video_task(job: CaptureJob, video: Path, probe: TaskOutcome) -> TaskOutcome:
    """Track the labels of one video into WS/batch/track/<video>/tracks.csv. Skipped while the video, the labels and
    the options are those of the last run (WS/batch/track/<video>/task.json keeps their hash)."""
    if probe.failed:
        return probe
    labels = job.options.labels
    assert labels is not None  # the graph has per-video track tasks only for captures with labels

    def body(outcome: TaskOutcome) -> None:
        folder = track_folder(job.workspace, video.stem)
        key = inputs_key({"video": video, "labels": labels}, {"track": job.options.track, "video": video.stem})
        out = folder / "tracks.csv"
        if not job.options.force and _cached(folder / TASK_NAME, {"inputs": key}) and out.is_file():
            outcome.status = "skipped"
            return
        folder.mkdir(parents=True, exist_ok=True)
        (folder / TASK_NAME).unlink(missing_ok=True)  # a task that fails half-way must not look done
        (folder / "labels.csv").write_bytes(labels.read_bytes())
        out.unlink(missing_ok=True)  # the tracker keeps rows of other videos from an old file: start clean
        track_run(folder, out, job.options.track, videos={video.stem: video})
        atomic_write_text(folder / TASK_NAME, json.dumps({"inputs": key}, indent=1) + "\n")

    return guarded(job, "track", video.stem, body)


def solve_task(job: CaptureJob, register: TaskOutcome, tracked: list[TaskOutcome]) -> TaskOutcome:
    """The rest of the pipeline in one task: `track` (the merge of the per-video files, when there are any),
    `subject`, `solve`, `record`, `export`, each skipped when `pipeline.json` says it is up to date."""
    failed = first_failure([register, *tracked])
    if failed is not None:
        return failed
    merge = None
    if tracked:
        parts = {video.stem: track_folder(job.workspace, video.stem) / "tracks.csv" for video in job.capture.videos}
        labels = job.options.labels
        assert labels is not None  # per-video tracks exist only with labels
        merge = lambda out: merge_tracks(parts, labels, out)  # noqa: E731

    def body(outcome: TaskOutcome) -> None:
        failed_background = RegistrationError(register.registration_error) if register.registration_error else None
        stages = job.stages()
        if stages.finish(failed_background, tracker=merge) is None:
            log.info("%s: no labels and no tracks: registration only", stages.ws)
        note_stages(outcome, stages)

    return guarded(job, "solve", None, body)


def run_capture(capture: Capture, out: str | Path, options: PipelineOptions | None = None) -> list[TaskOutcome]:
    """One capture in this process, without Dask: the probes, then the pipeline's own stages in order (the serial
    tracker over all videos, not the per-video tasks). What a batch of this one capture computes."""
    job = job_for(capture, Path(out), options or PipelineOptions())
    outcomes = [probe_task(job, video) for video in capture.videos]
    register = register_task(job, outcomes)
    outcomes.append(register)
    outcomes.append(solve_task(job, register, []))
    return outcomes


# ----------------------------------------------------------------------------------------------------------
# The per-video tracks, merged


def merge_tracks(parts: dict[str, Path], labels: Path, out: Path) -> Path:
    """One tracks.csv from per-video tracker outputs, as the tracker writes it for all videos at once: each video's
    rows from its own file, and the point order of first appearance (videos in capture order, points in label
    order), which decides the row order within a frame."""
    order: dict[str, list[str]] = {}
    for video, _, point in read_labels(labels):
        points = order.setdefault(video, [])
        if point not in points:
            points.append(point)
    rows: list[tuple[str, int, str, float, float]] = []
    source: list[str] = []
    score: list[str] = []
    others: Tracks | None = None
    for video, path in parts.items():
        tracks = read_tracks(path)
        others = tracks if others is None else others
        rank = {p: i for i, p in enumerate(order.get(video, []))}
        mine = [i for i in range(len(tracks)) if tracks.video[i] == video]
        mine.sort(key=lambda i: (rank.get(tracks.point[i], len(rank)), int(tracks.frame[i])))
        _take(tracks, mine, rows, source, score)
    if others is not None:  # labels of videos the capture does not have: the tracker keeps them as label rows
        foreign = [i for i in range(len(others)) if others.video[i] not in parts]
        _take(others, foreign, rows, source, score)
    return write_tracks(out, Tracks.from_rows(rows, source=source, score=score))


def _take(
    tracks: Tracks,
    index: list[int],
    rows: list[tuple[str, int, str, float, float]],
    source: list[str],
    score: list[str],
) -> None:
    sources = tracks.extra.get("source", [""] * len(tracks))
    scores = tracks.extra.get("score", [""] * len(tracks))
    for i in index:
        rows.append(
            (tracks.video[i], int(tracks.frame[i]), tracks.point[i], float(tracks.xy[i, 0]), float(tracks.xy[i, 1]))
        )
        source.append(sources[i])
        score.append(scores[i])


def track_folder(workspace: Path, video: str) -> Path:
    return workspace / BATCH_DIR / TRACK_DIR / video


def _cached(path: Path, stamp: dict[str, Any]) -> bool:
    """Whether the JSON file at `path` holds every key of `stamp` with the same value."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(document, dict) and all(document.get(k) == v for k, v in stamp.items())


def note_stages(outcome: TaskOutcome, stages: Stages) -> None:
    outcome.pipeline = {s.name: None if s.skipped else round(s.seconds, 3) for s in stages.result.stages}
    if all(v is None for v in outcome.pipeline.values()):  # none ran (or none applies: registration only)
        outcome.status = "skipped"


__all__ = [
    "STAGES",
    "CaptureJob",
    "TaskOutcome",
    "first_failure",
    "guarded",
    "job_for",
    "merge_tracks",
    "note_stages",
    "probe_task",
    "register_task",
    "run_capture",
    "solve_task",
    "track_video_task",
]
