"""The page's "track" button: runs the tracking stage in a background thread, one run at a time.

The page starts a run and polls its status; the tracker reads `WS/labels.csv` and rewrites `WS/tracks.csv`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

from dynrecon.errors import DynreconError

log = logging.getLogger(__name__)

# (workspace, {video name: video file} to track) -> path of the tracks.csv written
TrackFunction = Callable[[Path, dict[str, Path]], Path]


def track_with_tracking_stage(workspace: Path, videos: dict[str, Path]) -> Path:
    """The real tracker: the tracking stage (`tracking.track`) on the workspace, limited to the given videos."""
    # Imported late: the server starts (and labels) even where the tracker's OpenCV cannot be imported.
    from tracking.stage import run

    return run(workspace, videos=videos)


class JobState(Enum):
    IDLE = "idle"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


@dataclass(kw_only=True)
class JobStatus:
    state: JobState = JobState.IDLE
    videos: list[str] = field(default_factory=list)
    message: str = ""
    seq: int = 0  # increments with every finished run, so the page knows when to reload tracks
    seconds: float = 0.0

    def as_json(self) -> dict:
        return {
            "state": self.state.value,
            "videos": self.videos,
            "message": self.message,
            "seq": self.seq,
            "seconds": round(self.seconds, 2),
        }


class TrackJob:
    def __init__(self, workspace: Path, track: TrackFunction):
        self.workspace = workspace
        self.track = track
        self._lock = threading.Lock()
        self._status = JobStatus()
        self._thread: threading.Thread | None = None

    def status(self) -> JobStatus:
        with self._lock:
            return replace(self._status)

    def running(self) -> bool:
        return self.status().state is JobState.RUNNING

    def start(self, videos: dict[str, Path]) -> bool:
        """Start a run; False when one is already running."""
        with self._lock:
            if self._status.state is JobState.RUNNING:
                return False
            self._status = JobStatus(
                state=JobState.RUNNING,
                videos=list(videos),
                seq=self._status.seq,
                message=f"tracking {', '.join(videos)}",
            )
            self._thread = threading.Thread(target=self._run, args=(videos,), name="track", daemon=True)
            self._thread.start()
            return True

    def wait(self, timeout: float | None = None) -> JobStatus:
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
        return self.status()

    def _run(self, videos: dict[str, Path]) -> None:
        start = time.perf_counter()
        try:
            out = self.track(self.workspace, videos)
            state, message = JobState.DONE, f"tracked {', '.join(videos)} -> {out.name}"
        except DynreconError as error:  # a user's mistake (e.g. a broken labels.csv): shown on the page
            state, message = JobState.FAILED, str(error)
        except Exception as error:  # a bug in the tracker: keep the server alive, show it, log the traceback
            log.exception("tracking failed")
            state, message = JobState.FAILED, f"tracker crashed: {type(error).__name__}: {error}"
        with self._lock:
            self._status = JobStatus(
                state=state,
                videos=list(videos),
                message=message,
                seq=self._status.seq + 1,
                seconds=time.perf_counter() - start,
            )
        log.info("%s (%.1f s)", message, time.perf_counter() - start)
