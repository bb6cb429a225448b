"""Many captures on Dask: `dynrecon batch`, and the same task graph from Python.

    import batch

    report = batch.run_batch(["captures/monday", "captures/tuesday"], "season", batch.BatchOptions(workers=2))
    report.failed  # capture names; season/batch.json has each capture's status, stage, seconds and error

    # or build the graph and compute it with any Dask scheduler:
    graphs = batch.build_graph([batch.read_capture("captures/monday")], "season")
    outcomes = dask.compute(*[g.final for g in graphs])  # batch.TaskOutcome per capture

    batch.run_capture(batch.read_capture("captures/monday"), "alone")  # one capture here, without Dask

The tasks run the stages of `dynrecon run` through its public stage API, `dynrecon.pipeline.Stages`, which is also
there for a graph of one's own (docs/scaling.md, "From Python", has a tested example).

A capture folder's layout is in docs/formats.md ("Capture folder"); docs/scaling.md says how to run on a cluster.
Names are loaded on first use: `import batch` does not load Dask or the stages.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dynrecon.lazy import lazy_exports

if TYPE_CHECKING:
    from batch.capture import Capture, read_capture
    from batch.graph import BatchOptions, BatchReport, CaptureGraph, build_graph, connect, run_batch
    from batch.state import BatchState, CaptureStatus
    from batch.tasks import CaptureJob, TaskOutcome, run_capture

# public name -> (module, attribute)
_FRONT = {
    "BatchOptions": ("batch.graph", "BatchOptions"),
    "BatchReport": ("batch.graph", "BatchReport"),
    "CaptureGraph": ("batch.graph", "CaptureGraph"),
    "build_graph": ("batch.graph", "build_graph"),
    "connect": ("batch.graph", "connect"),
    "run_batch": ("batch.graph", "run_batch"),
    "Capture": ("batch.capture", "Capture"),
    "read_capture": ("batch.capture", "read_capture"),
    "BatchState": ("batch.state", "BatchState"),
    "CaptureStatus": ("batch.state", "CaptureStatus"),
    "CaptureJob": ("batch.tasks", "CaptureJob"),
    "TaskOutcome": ("batch.tasks", "TaskOutcome"),
    "run_capture": ("batch.tasks", "run_capture"),
}

__all__ = [
    "BatchOptions",
    "BatchReport",
    "BatchState",
    "Capture",
    "CaptureGraph",
    "CaptureJob",
    "CaptureStatus",
    "TaskOutcome",
    "build_graph",
    "connect",
    "read_capture",
    "run_batch",
    "run_capture",
]


__getattr__, __dir__ = lazy_exports(__name__, _FRONT)
