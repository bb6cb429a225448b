"""The SfM registration of one capture as tasks (`sfm.per_video`): per video, plan (motion test, keyframes, SfM
images) and feature extraction; per capture, merge, matching and mapping; per video, in-between posing
(localize); per capture, the finish (subject path, cameras.json, report) inside the pipeline's `register` stage.

    plan v (per video) -> extract v (per video, after every plan) -> map -> localize v (per video) -> register

Each task reads and writes files in WS/register/ (docs/formats.md, "Per-video registration files") and returns a
small `TaskOutcome`. While the pipeline's `register` stage is up to date (`pipeline.json`), every one of them is
skipped; the last one records the stage with the same hash as `dynrecon run`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from batch.tasks import CaptureJob, TaskOutcome, first_failure, guarded, note_stages
from dynrecon.pipeline import REGISTER_DIR
from sfm.options import RegisterOptions
from sfm.per_video import capture_facts, clear_outputs, extract_videos, localize_video, prepare_video
from sfm.stage import RegistrationError, capture_tracks, finish_capture, map_capture
from sfm.video import probe_video

log = logging.getLogger(__name__)


def _folder(job: CaptureJob) -> Path:
    return job.workspace / REGISTER_DIR


def _options(job: CaptureJob) -> RegisterOptions:
    return job.stages().background_options()


def _names(job: CaptureJob) -> list[str]:
    return [video.stem for video in job.capture.videos]


def _up_to_date(job: CaptureJob) -> bool:
    return job.stages().register_up_to_date()


def plan_task(job: CaptureJob, video: Path, probe: TaskOutcome) -> TaskOutcome:
    """One video's plan and SfM images (WS/register/sfm/videos/<video>/plan.json, frames/<video>/, masks)."""
    if probe.failed:
        return probe

    def body(outcome: TaskOutcome) -> None:
        if _up_to_date(job):
            outcome.status = "skipped"
            return
        folder = _folder(job)
        clear_outputs(folder)  # every plan task of the capture does it: removing a missing file is harmless
        options = _options(job)
        prepare_video(probe_video(video), folder, options, capture_tracks(options, folder, _names(job)))

    return guarded(job, "plan", video.stem, body)


def extract_task(job: CaptureJob, video: Path, plans: list[TaskOutcome]) -> TaskOutcome:
    """One video's SIFT features into WS/register/sfm/features/<video>.db (after every plan of the capture: the
    descriptor kind and masks depend on all videos)."""
    failed = first_failure(plans)
    if failed is not None:
        return failed

    def body(outcome: TaskOutcome) -> None:
        if _up_to_date(job):
            outcome.status = "skipped"
            return
        folder, names = _folder(job), _names(job)
        extract_videos(folder, [video.stem], _options(job), capture_facts(folder, names, _options(job)))

    return guarded(job, "extract", video.stem, body)


def map_task(job: CaptureJob, extracts: list[TaskOutcome]) -> TaskOutcome:
    """The capture's merge of the feature databases, matching and mapping (WS/register/sfm/mapping.json)."""
    failed = first_failure(extracts)
    if failed is not None:
        return failed

    def body(outcome: TaskOutcome) -> None:
        if _up_to_date(job):
            outcome.status = "skipped"
            return
        map_capture(_folder(job), _names(job), _options(job))

    return guarded(job, "map", None, body)


def localize_task(job: CaptureJob, video: Path, mapped: TaskOutcome) -> TaskOutcome:
    """Every wanted frame's pose of one video (WS/register/sfm/videos/<video>/poses.json)."""
    if mapped.failed:
        return mapped

    def body(outcome: TaskOutcome) -> None:
        if _up_to_date(job):
            outcome.status = "skipped"
            return
        localize_video(_folder(job), video.stem, _options(job))

    return guarded(job, "localize", video.stem, body)


def finish_register_task(job: CaptureJob, localized: list[TaskOutcome]) -> TaskOutcome:
    """The pipeline's `register` stage, its SfM done by the tasks before: the subject path, cameras.json,
    background.ply and register_report.json, recorded in pipeline.json with the hash of `dynrecon run`."""
    failed = first_failure(localized)
    if failed is not None:
        return failed
    names = _names(job)

    def finish(videos: list[Path], folder: Path, options: RegisterOptions) -> None:
        finish_capture(folder, names, options, capture_tracks(options, folder, names))

    def body(outcome: TaskOutcome) -> None:
        stages = job.stages()
        background_failed: RegistrationError | None = stages.register(registrar=finish)
        outcome.registration_error = str(background_failed) if background_failed is not None else None
        note_stages(outcome, stages)

    return guarded(job, "register", None, body)


__all__ = ["extract_task", "finish_register_task", "localize_task", "map_task", "plan_task"]
