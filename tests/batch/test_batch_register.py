"""A capture without a calibration through `dynrecon batch`: its SfM registration as per-video tasks (plan, extract,
localize) around one mapping task, on a real scheduler and two real worker processes on 127.0.0.1. The cameras
are byte for byte those of the capture run alone (`batch.run_capture`: the pipeline's serial `register`), COLMAP
on one thread; a rerun skips every task. The synthetic room, 3 moving cameras of 10/8/6 frames at 480 x 360."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from batch import BatchOptions, read_capture, run_batch, run_capture
from batch.graph import build_graph
from dynrecon.pipeline import PipelineOptions, default_register
from sfm.layout import Layout
from sfm.synthetic.demo import render_demo, three_cameras

DASK = Path(sys.executable).parent / "dask"
REGISTER_TASKS = ["extract"] * 3 + ["localize"] * 3 + ["map"] + ["plan"] * 3 + ["probe"] * 3 + ["register", "solve"]


def _options() -> PipelineOptions:
    # One COLMAP thread: the mapper is then deterministic, so "identical" means byte for byte.
    register = replace(default_register(), long_side=480, max_frames=6, max_features=1500, num_threads=1)
    return PipelineOptions(register=register)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture(scope="module")
def address(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`dask scheduler` and two `dask worker` processes of one thread each."""
    from distributed import Client

    logs = tmp_path_factory.mktemp("cluster")
    port = _free_port()
    processes = []

    def start(name: str, *args: str) -> None:
        log = (logs / f"{name}.log").open("w")
        processes.append(subprocess.Popen([str(DASK), *args], stdout=log, stderr=subprocess.STDOUT))

    start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard")
    for i in range(2):
        start(f"worker{i}", "worker", f"tcp://127.0.0.1:{port}", "--nthreads", "1", "--no-dashboard")
    try:
        with Client(f"tcp://127.0.0.1:{port}", timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield f"tcp://127.0.0.1:{port}"
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("captures") / "room"
    render_demo(folder, three_cameras(480, 360, frames=(10, 8, 6)))
    return folder


def test_the_graph_of_an_sfm_capture_has_per_video_registration_tasks(room: Path, tmp_path: Path) -> None:
    graph = build_graph([read_capture(room)], tmp_path)[0]
    assert sorted(key.split("-")[1] for key in graph.tasks) == REGISTER_TASKS


@pytest.mark.slow
def test_per_video_registration_tasks_give_the_cameras_of_the_capture_alone(
    room: Path, address: str, tmp_path: Path
) -> None:
    out = tmp_path / "season"
    report = run_batch([room], out, BatchOptions(pipeline=_options(), scheduler=address, progress=False))
    assert not report.failed, report.captures
    alone = tmp_path / "alone"
    assert all(not o.failed for o in run_capture(read_capture(room), alone, _options()))

    for name in ("cameras.json", "background.ply"):
        assert (out / "room" / "register" / name).read_bytes() == (alone / "room" / "register" / name).read_bytes()
    pipeline = json.loads((out / "room" / "pipeline.json").read_text())["stages"]["register"]
    assert (
        pipeline["inputs"] == json.loads((alone / "room" / "pipeline.json").read_text())["stages"]["register"]["inputs"]
    )
    layout = Layout(out / "room" / "register")
    assert all(layout.features(v).is_file() and layout.poses(v).is_file() for v in ("cam0", "cam1", "cam2"))
    state = json.loads((out / "batch.json").read_text())["captures"]["room"]
    assert set(state["seconds"]) >= {"probe", "plan", "extract", "map", "localize", "register", "solve"}
    registered = json.loads((out / "room" / "register" / "register_report.json").read_text())
    assert registered["ok"] and set(registered["timings_s"]) >= {"decode", "extract", "match", "map", "localize"}

    again = run_batch([room], out, BatchOptions(pipeline=_options(), scheduler=address, progress=False))
    assert again.captures["room"].status == "done" and again.captures["room"].ran == []
