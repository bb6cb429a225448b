"""`DIR/batch.json`: per capture, its status, the stage it reached, seconds per stage and the one-line error.

Written atomically after every finished task, so that a lab can watch it (or a crashed client leaves the last
state). The stage hashes that decide what a rerun skips are in each workspace's `pipeline.json`, not here.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from batch.tasks import STAGES, TaskOutcome
from dynrecon.atomic import atomic_write_text

log = logging.getLogger(__name__)

STATE_NAME = "batch.json"
VERSION = 1


@dataclass(kw_only=True)
class CaptureStatus:
    name: str
    folder: str
    workspace: str | None = None  # None when the folder could not be read
    status: str = "pending"  # pending, running, done, failed, interrupted (stopped with the batch; a rerun resumes)
    stage: str | None = None  # the last stage that finished, or the one that failed
    error: str | None = None  # one line
    seconds: dict[str, float] = field(default_factory=dict)  # batch stage -> task seconds (summed over videos)
    ran: list[str] = field(default_factory=list)  # batch stages that did work this run (the others were up to date)
    pipeline: dict[str, float | None] = field(default_factory=dict)  # pipeline stage -> seconds, None: skipped
    finished: str | None = None

    def note(self, outcome: TaskOutcome) -> None:
        """Fold one finished task into the status (a failure keeps the first reason)."""
        if self.status == "failed":
            return
        self.seconds[outcome.stage] = round(self.seconds.get(outcome.stage, 0.0) + outcome.seconds, 3)
        if outcome.status == "done" and outcome.stage not in self.ran:
            self.ran.append(outcome.stage)
            self.ran.sort(key=STAGES.index)
        self.pipeline.update(outcome.pipeline)
        if outcome.failed:
            where = (
                f" ({outcome.video})" if outcome.video and outcome.error and outcome.video not in outcome.error else ""
            )
            self.fail(outcome.stage, f"{outcome.error}{where}")
            return
        self.status = "running"
        if self.stage is None or STAGES.index(outcome.stage) >= STAGES.index(self.stage):
            self.stage = outcome.stage

    def fail(self, stage: str, error: str) -> None:
        self.status, self.stage, self.error = "failed", stage, error
        self.finished = _now()

    def done(self) -> None:
        self.status, self.stage, self.finished = "done", STAGES[-1], _now()

    def interrupt(self) -> None:
        """Stopped with the batch (Ctrl+C) while pending or running: `stage` stays the last one that finished."""
        if self.status in ("pending", "running"):
            self.status, self.finished = "interrupted", _now()


class BatchState:
    """The captures of `DIR/batch.json`; captures of earlier runs that this run does not name are kept."""

    def __init__(self, out: Path) -> None:
        self.path = out / STATE_NAME
        self.captures: dict[str, CaptureStatus] = {}
        if self.path.is_file():
            try:
                document = json.loads(self.path.read_text(encoding="utf-8"))
                for name, entry in document.get("captures", {}).items():
                    self.captures[name] = CaptureStatus(**{**entry, "name": name})
            except (OSError, ValueError, TypeError, AttributeError):
                log.warning("%s is not a batch state file; starting a new one", self.path)
                self.captures = {}

    def start(self, name: str, folder: Path, workspace: Path | None) -> CaptureStatus:
        status = CaptureStatus(name=name, folder=str(folder), workspace=str(workspace) if workspace else None)
        self.captures[name] = status
        return status

    def save(self) -> None:
        document: dict[str, Any] = {
            "version": VERSION,
            "updated": _now(),
            "captures": {
                name: {k: v for k, v in asdict(s).items() if k != "name"} for name, s in self.captures.items()
            },
        }
        atomic_write_text(self.path, json.dumps(document, indent=1) + "\n")


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
