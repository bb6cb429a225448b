"""The batch's task graph on Dask, and running it: a LocalCluster by default, or a remote scheduler.

`build_graph` makes, per capture, `dask.delayed` tasks (see `batch.tasks`): one probe per video, the registration
(one task importing a calibration, or SfM as per-video plan, extract and localize tasks around one map task and one
register task: `batch.register_tasks`), one track per video (with labels), one solve. Their arguments are paths
and options and their results `TaskOutcome`s, so nothing large passes through the scheduler; the workspace lives on
a filesystem every worker sees. `run_batch` computes the graph, folds each finished task into `DIR/batch.json` and
the progress bar, and reports a failing capture without stopping the others. Dask retries a task that raised
(`retries`) and reschedules the tasks of a lost worker (`distributed.scheduler.allowed-failures`).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dask
from dask.delayed import Delayed
from distributed import Client, Future, LocalCluster, WorkerPlugin, wait
from tqdm import tqdm

from batch.capture import Capture, read_capture
from batch.register_tasks import extract_task, finish_register_task, localize_task, map_task, plan_task
from batch.state import BatchState, CaptureStatus
from batch.tasks import (
    CaptureJob,
    TaskOutcome,
    job_for,
    one_line,
    probe_task,
    register_task,
    solve_task,
    track_video_task,
)
from dynrecon.atomic import require_writable
from dynrecon.errors import DynreconError, InputError
from dynrecon.pipeline import PipelineOptions
from sfm.options import declared_offsets

log = logging.getLogger(__name__)

# The workers' per-video progress bars would garble the batch's own, on the same terminal.
WORKER_ENV = {"TQDM_DISABLE": "1"}
POLL_S = 5.0  # how often a batch that waits for its tasks checks that the cluster still has workers


@dataclass(kw_only=True)
class BatchOptions:
    pipeline: PipelineOptions = field(default_factory=PipelineOptions)  # every capture's `dynrecon run` options
    scheduler: str | None = None  # address of a running scheduler (tcp://host:8786); None: a LocalCluster here
    workers: int | None = None  # LocalCluster: worker processes (default: one per core); remote: wait for as many
    retries: int = 2  # extra tries of a task that raised (a user error fails at once)
    wait_s: float = 120.0  # how long to wait for the scheduler and the workers
    progress: bool = True  # the progress bar and one line per finished capture


@dataclass(kw_only=True)
class CaptureGraph:
    """One capture's tasks: `tasks` by key in the order they become ready; `final` is the solve task."""

    job: CaptureJob
    tasks: dict[str, Delayed]
    final: Delayed


@dataclass(kw_only=True)
class BatchReport:
    out: Path
    captures: dict[str, CaptureStatus]

    @property
    def failed(self) -> list[str]:
        return [name for name, s in self.captures.items() if s.status == "failed"]


def build_graph(
    captures: Sequence[Capture], out: str | Path, options: BatchOptions | None = None
) -> list[CaptureGraph]:
    """The task graph of `captures` with workspaces under `out` (`out/<capture name>`). Compute the `final` tasks
    with any Dask scheduler (`dask.compute(*[g.final for g in graphs])`); each returns a `TaskOutcome`."""
    options = options or BatchOptions()
    out = Path(out).resolve()
    token = uuid.uuid4().hex[:8]  # fresh keys per build: two batches on one scheduler never share results
    return [_capture_graph(job_for(capture, out, options.pipeline), token) for capture in captures]


def _capture_graph(job: CaptureJob, token: str) -> CaptureGraph:
    """Keys `dynrecon-<stage>-<capture>[-<video>]-<token>`: the stage is the second word (`_outcome` reads it)."""
    tasks: dict[str, Delayed] = {}

    def task(function: Any, stage: str, video: str | None, *args: Any) -> Delayed:
        key = "-".join(["dynrecon", stage, job.name, *([video] if video else []), token])
        tasks[key] = dask.delayed(function, pure=False)(*args, dask_key_name=key)
        return tasks[key]

    videos = job.capture.videos
    probes = {video.stem: task(probe_task, "probe", video.stem, job, video) for video in videos}
    if job.options.calibration is None:  # SfM: per-video plan, extract and localize tasks around one mapping
        plans = [task(plan_task, "plan", v.stem, job, v, probes[v.stem]) for v in videos]
        extracts = [task(extract_task, "extract", v.stem, job, v, plans) for v in videos]
        mapped = task(map_task, "map", None, job, extracts)
        localized = [task(localize_task, "localize", v.stem, job, v, mapped) for v in videos]
        register = task(finish_register_task, "register", None, job, [*probes.values(), *localized])
    else:
        register = task(register_task, "register", None, job, list(probes.values()))
    tracked = []
    if job.options.labels is not None and job.options.tracks is None:
        tracked = [task(track_video_task, "track", video.stem, job, video, probes[video.stem]) for video in videos]
    final = task(solve_task, "solve", None, job, register, tracked)
    return CaptureGraph(job=job, tasks=tasks, final=final)


def run_batch(captures: Sequence[str | Path], out: str | Path, options: BatchOptions | None = None) -> BatchReport:
    """Reconstruct every capture folder into `out/<name>/` on Dask; `out/batch.json` says how each went. Folders
    that cannot be read fail at once, with their one-line reason; the others run."""
    options = options or BatchOptions()
    out = require_writable(Path(out).resolve())  # one line where it cannot be made
    out.mkdir(parents=True, exist_ok=True)
    state = BatchState(out)
    good = _read_captures(captures, state, out, options.progress, options.pipeline)
    state.save()
    graphs = build_graph(good, out, options)
    if graphs:
        try:
            with connect(options) as client:
                _compute(client, graphs, state, options)
        except KeyboardInterrupt:  # batch.json must not say "running" for captures nothing runs any more
            for capture in good:
                state.captures[capture.name].interrupt()
            state.save()
            raise
    return BatchReport(out=out, captures={c.name: state.captures[c.name] for c in good} | _unread(state, captures))


def _read_captures(
    folders: Sequence[str | Path], state: BatchState, out: Path, echo: bool, pipeline: PipelineOptions
) -> list[Capture]:
    read: list[tuple[Path, Capture | DynreconError]] = []
    seen: dict[str, Path] = {}
    for folder in folders:
        path = Path(folder).resolve()
        try:
            capture = read_capture(path)
            if capture.name in seen:
                raise InputError(path, f"capture name {capture.name!r} is also {seen[capture.name]}", fix="rename one")
            # --offsets name the videos of every capture: one without them fails here, before any work
            declared_offsets(pipeline.register.synchronized, pipeline.register.offsets, capture.video_names)
        except DynreconError as error:
            read.append((path, error))
            continue
        seen[capture.name] = path
        read.append((path, capture))
    good: list[Capture] = []
    for path, outcome in read:
        if isinstance(outcome, Capture):
            state.start(outcome.name, path, out / outcome.name)
            good.append(outcome)
            continue
        # keyed by its folder's name, or by its path where a capture that runs has that name (its entry stays)
        status = state.start(str(path) if path.name in seen else path.name, path, None)
        status.fail("read", one_line(outcome))
        _echo(echo, f"{path.name}: failed (read): {status.error}")
    return good


def _unread(state: BatchState, folders: Sequence[str | Path]) -> dict[str, CaptureStatus]:
    names = {Path(f).resolve().name for f in folders} | {str(Path(f).resolve()) for f in folders}
    return {n: s for n, s in state.captures.items() if n in names and s.workspace is None}


def _compute(client: Client, graphs: list[CaptureGraph], state: BatchState, options: BatchOptions) -> None:
    delayed = [d for g in graphs for d in g.tasks.values()]
    owner = {key: g for g in graphs for key in g.tasks}
    futures: list[Future] = client.compute(delayed, retries=options.retries)
    remaining = {g.job.name: len(g.tasks) for g in graphs}
    with tqdm(total=len(futures), desc="batch", unit="task", disable=not options.progress) as bar:
        for future in _finished(client, futures, options.wait_s):
            graph = owner[str(future.key)]
            status = state.captures[graph.job.name]
            status.note(_outcome(future, graph))
            remaining[graph.job.name] -= 1
            if remaining[graph.job.name] == 0 and status.status != "failed":
                status.done()
            state.save()
            bar.set_postfix_str(_summary(state, graphs), refresh=False)
            bar.update(1)
            if remaining[graph.job.name] == 0:
                _echo(options.progress, _line(status), bar)


def _finished(client: Client, futures: list[Future], wait_s: float) -> Iterator[Future]:
    """`futures` as they finish; an error, instead of waiting forever, when the cluster has had no worker for
    `wait_s` seconds (all lost, or none ever joined)."""
    pending = set(futures)
    alone_since: float | None = None
    while pending:
        try:
            done, pending = wait(list(pending), timeout=POLL_S, return_when="FIRST_COMPLETED")
        except TimeoutError:
            done = set()
        yield from (f for f in futures if f in done)
        if done or client.scheduler_info()["workers"]:
            alone_since = None
            continue
        alone_since = alone_since or time.monotonic()
        if time.monotonic() - alone_since > wait_s:
            raise InputError(
                None,
                f"the Dask cluster has had no worker for {wait_s:.0f} s ({len(pending)} tasks left)",
                fix="start workers (`dask worker ADDRESS`) and run the same command again: finished work is kept",
            )


def _outcome(future: Future, graph: CaptureGraph) -> TaskOutcome:
    """The task's outcome; an exception after Dask's retries (or a worker lost too often) as a failed one."""
    stage = str(future.key).split("-")[1]
    try:
        # result(), not status: a finished task whose result sat on a worker lost since is computed again
        outcome: TaskOutcome = future.result()
        return outcome
    except Exception as error:
        return TaskOutcome(capture=graph.job.name, stage=stage, status="failed", error=one_line(error))


def _summary(state: BatchState, graphs: list[CaptureGraph]) -> str:
    statuses = [state.captures[g.job.name].status for g in graphs]
    return f"{statuses.count('done')}/{len(graphs)} captures done, {statuses.count('failed')} failed"


def _line(status: CaptureStatus) -> str:
    if status.status == "failed":
        return f"{status.name}: failed ({status.stage}): {status.error}"
    ran = ", ".join(f"{s} {status.seconds.get(s, 0.0):.1f} s" for s in status.ran) or "everything up to date"
    return f"{status.name}: done ({ran})"


def _echo(enabled: bool, line: str, bar: tqdm | None = None) -> None:
    if enabled:
        (bar or tqdm).write(line)


@contextmanager
def connect(options: BatchOptions) -> Iterator[Client]:
    """A client of `options.scheduler`, or of a LocalCluster of worker processes on this machine."""
    if options.scheduler:
        try:
            client = Client(options.scheduler, timeout=f"{options.wait_s}s")
        except OSError as error:
            raise InputError(None, f"cannot reach the scheduler {options.scheduler}: {error}") from None
        with client:
            if options.workers:
                client.wait_for_workers(options.workers, timeout=options.wait_s)
            yield client
        return
    workers = options.workers or max(1, os.cpu_count() or 1)
    # Processes, one thread each: the stages hold the GIL in Python loops, and COLMAP and OpenCV bring their own
    # threads.
    with local_cluster(workers) as cluster, Client(cluster) as client:
        client.register_plugin(LeaveCtrlCToTheBatch())
        try:
            yield client
        except KeyboardInterrupt:  # the workers are stopped mid-task: Dask's warnings that they were are expected
            logging.getLogger("distributed").setLevel(logging.ERROR)
            raise


class LeaveCtrlCToTheBatch(WorkerPlugin):
    """A local worker ignores SIGINT. Ctrl+C reaches the terminal's whole process group: the workers and their stages
    would each print a traceback and report the stage as failed, while the batch stops them itself (its cluster
    shuts them down, and a stage's child process ends with its worker). Only local workers: a `dask worker` the user
    started keeps its Ctrl+C."""

    def setup(self, worker: Any) -> None:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def local_cluster(workers: int) -> LocalCluster:
    """Worker processes on this machine, one thread each, with the environment the stages run fast in."""
    # Dask's nanny sets MALLOC_TRIM_THRESHOLD_, which turns off glibc's adaptive mmap threshold: every frame buffer
    # is then mapped and unmapped again, and the tracker slows down several times (docs/scaling.md). The worker's
    # statistical profiler walks the running task's stack many times a second in the worker's event loop: CPU taken
    # beside every one-thread worker's task (docs/scaling.md), for a dashboard page the batch does not show.
    settings = {
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
        "distributed.worker.profile.enabled": False,
    }
    with dask.config.set(settings):
        return LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0", env=WORKER_ENV
        )
