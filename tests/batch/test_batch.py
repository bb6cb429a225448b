"""`dynrecon batch` on a real scheduler and two real worker processes on 127.0.0.1, and on the embedded LocalCluster.

One batch of three small simulated captures (one with ready tracks, two whose labels each video's task tracks) and
four bad ones. While it runs, the worker that is solving a capture is killed: the batch must still finish, with
results identical to each capture run alone (`batch.run_capture`, the pipeline's serial stages, no Dask). The bad
captures (broken tracks, no videos, an undecodable video, a missing calibration) each get a one-line reason in
batch.json and on screen. A rerun skips everything. The cluster is shared by the module's tests, the captures are
tiny (3 points, 1 s, 320 px): the module takes well under a minute.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from batch import read_capture, run_capture
from batch.synthetic import Inputs, SimulatedCaptureOptions, simulated_capture
from dynrecon import cli

GOOD = ("walk", "jump", "throw")
BAD = ("broken_tracks", "empty", "undecodable", "no_calibration")
# Outputs compared byte for byte with the capture run alone (report.json without its paths and timings).
SAME_BYTES = (
    "register/cameras.json",
    "tracks.csv",
    "points3d.csv",
    "sequencing.json",
    "points.trc",
    "points.c3d",
)
DASK = Path(sys.executable).parent / "dask"


def _options(seed: int, inputs: Inputs) -> SimulatedCaptureOptions:
    # Three points take the solver's few-points path: a solve of ~1 s, and still every stage of `dynrecon run`.
    return SimulatedCaptureOptions(seed=seed, inputs=inputs, points=3, seconds=1.0)


@pytest.fixture(scope="module")
def captures(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("captures")
    folders = {
        "walk": simulated_capture(root / "walk", _options(1, Inputs.TRACKS)),
        "jump": simulated_capture(root / "jump", _options(2, Inputs.LABELS)),
        "throw": simulated_capture(root / "throw", _options(3, Inputs.LABELS)),
    }
    broken = shutil.copytree(folders["walk"], root / "broken_tracks")
    (broken / "tracks.csv").write_text("video,frame\ncam0,zero\n")  # fails on a worker: its inputs, checked first
    (root / "empty").mkdir()
    undecodable = shutil.copytree(folders["walk"], root / "undecodable")
    (undecodable / "cam1.avi").write_bytes(b"\x00not a video" * 100)  # fails on a worker, in its probe task
    missing = shutil.copytree(folders["walk"], root / "no_calibration")
    (missing / "calibration.toml").unlink()
    (missing / "capture.json").write_text(json.dumps({"calibration": "calibration.toml"}))
    return {**folders, "broken_tracks": broken, "empty": root / "empty", "undecodable": undecodable} | {
        "no_calibration": missing
    }


@dataclass
class Cluster:
    address: str
    scheduler: subprocess.Popen
    workers: dict[str, subprocess.Popen]  # worker address -> process


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """`dask scheduler` and two `dask worker` processes (no nanny: a killed worker stays dead)."""
    from distributed import Client

    logs = tmp_path_factory.mktemp("cluster")
    address = f"tcp://127.0.0.1:{_free_port()}"
    port = address.rsplit(":", 1)[1]

    def start(name: str, *args: str) -> subprocess.Popen:
        log = (logs / f"{name}.log").open("w")
        return subprocess.Popen([str(DASK), *args], stdout=log, stderr=subprocess.STDOUT)

    scheduler = start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard")
    workers = {}
    for i in range(2):
        worker_address = f"tcp://127.0.0.1:{_free_port()}"
        workers[worker_address] = start(
            f"worker{i}",
            "worker",
            address,
            "--nthreads",
            "1",
            "--no-nanny",
            "--no-dashboard",
            "--host",
            "127.0.0.1",
            "--worker-port",
            worker_address.rsplit(":", 1)[1],
        )
    try:
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield Cluster(address=address, scheduler=scheduler, workers=workers)
    finally:
        for process in [*workers.values(), scheduler]:
            process.terminate()
        for process in [*workers.values(), scheduler]:
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()


def _kill_a_solving_worker(cluster: Cluster, killed: dict[str, str], stop: threading.Event) -> None:
    """Kill the first worker seen solving a capture (mid-task), and note which task it held; watch until the batch
    ends (`stop`), however slow a loaded machine makes it."""
    from distributed import Client

    with Client(cluster.address, timeout="30s") as client:
        while not stop.is_set() and not killed:
            for worker, keys in client.processing().items():
                solving = [str(k) for k in keys if str(k).startswith("dynrecon-solve-")]
                if solving and worker in cluster.workers:
                    cluster.workers[worker].kill()
                    killed.update(worker=worker, task=solving[0])
                    return
            time.sleep(0.02)


def _batch(argv: list[str]) -> tuple[int, str]:
    screen = io.StringIO()
    with contextlib.redirect_stdout(screen), contextlib.redirect_stderr(screen):
        code = cli.main(["batch", *argv])
    return code, screen.getvalue()


def _state(out: Path) -> dict:
    return json.loads((out / "batch.json").read_text())["captures"]


@pytest.fixture(scope="module")
def first_batch(captures: dict[str, Path], cluster: Cluster, tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("season")
    killed: dict[str, str] = {}
    stop = threading.Event()
    killer = threading.Thread(target=_kill_a_solving_worker, args=(cluster, killed, stop))
    killer.start()
    started = time.perf_counter()
    try:
        folders = [str(captures[n]) for n in GOOD + BAD]
        code, screen = _batch([*folders, "--out", str(out), "--scheduler", cluster.address, "--workers", "2"])
    finally:
        stop.set()
        killer.join()
    seconds = time.perf_counter() - started
    return out, code, screen, killed, seconds


@pytest.fixture(scope="module")
def alone(captures: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("alone")
    for name in GOOD:
        assert all(not o.failed for o in run_capture(read_capture(captures[name]), out))
    return out


def _report(path: Path) -> dict:
    """report.json without what differs between runs of the same inputs: its input paths and its timings."""

    def strip(value):
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items() if k not in ("inputs", "timings")}
        return [strip(v) for v in value] if isinstance(value, list) else value

    return strip(json.loads(path.read_text()))


def _assert_same_results(out: Path, reference: Path) -> None:
    for name in GOOD:
        for relative in SAME_BYTES:
            assert (out / name / relative).read_bytes() == (reference / name / relative).read_bytes(), (
                f"{name}/{relative} differs"
            )
        assert _report(out / name / "report.json") == _report(reference / name / "report.json")
        assert (out / name / "recording.rrd").stat().st_size > 0


def test_a_lost_worker_does_not_stop_the_batch(first_batch) -> None:
    out, code, screen, killed, seconds = first_batch
    assert killed, f"no worker was seen solving a capture during the {seconds:.0f} s batch"
    state = _state(out)
    assert [state[n]["status"] for n in GOOD] == ["done"] * 3, screen
    assert code == 1  # the bad captures failed
    for name in GOOD:
        assert state[name]["stage"] == "solve" and state[name]["error"] is None
        assert set(state[name]["pipeline"]) >= {"register", "solve", "record", "export"}


def test_results_are_those_of_each_capture_run_alone(first_batch, alone: Path) -> None:
    out = first_batch[0]
    _assert_same_results(out, alone)
    # the per-video tracking tasks ran for the labelled captures, and their merge is the tracker's own file. (Not
    # `ran`: a task whose result sat on the killed worker runs again, finds its work done and says "skipped".)
    for name in ("jump", "throw"):
        assert "track" in _state(out)[name]["seconds"]
        for video in ("cam0", "cam1", "cam2"):
            assert (out / name / "batch" / "track" / video / "task.json").is_file()


@pytest.mark.parametrize(
    ("name", "stage", "reason"),
    [
        ("broken_tracks", "register", "header lacks column(s) point, x, y"),
        ("empty", "read", "no videos"),
        ("undecodable", "probe", "cam1.avi"),
        ("no_calibration", "read", "calibration file not found"),
    ],
)
def test_a_bad_capture_gets_a_one_line_reason_and_the_batch_goes_on(first_batch, name, stage, reason) -> None:
    out, _, screen, _, _ = first_batch
    entry = _state(out)[name]
    assert entry["status"] == "failed" and entry["stage"] == stage
    assert reason in entry["error"] and "\n" not in entry["error"]
    assert f"{name}: failed ({stage}): {entry['error']}" in screen.splitlines()


def test_a_rerun_skips_everything(first_batch, captures: dict[str, Path], cluster: Cluster) -> None:
    out = first_batch[0]
    before = {n: (out / n / "pipeline.json").read_bytes() for n in GOOD}
    code, screen = _batch([*(str(captures[n]) for n in GOOD), "--out", str(out), "--scheduler", cluster.address])
    assert code == 0, screen
    state = _state(out)
    for name in GOOD:
        assert state[name]["status"] == "done" and state[name]["ran"] == [], state[name]
        assert all(seconds is None for seconds in state[name]["pipeline"].values())
        assert (out / name / "pipeline.json").read_bytes() == before[name]
        assert f"{name}: done (everything up to date)" in screen
    assert state["empty"]["status"] == "failed"  # captures this run did not name keep their entries


def test_the_embedded_local_cluster_runs_the_same_batch(first_batch, captures: dict[str, Path], tmp_path: Path) -> None:
    code, screen = _batch([*(str(captures[n]) for n in GOOD), "--out", str(tmp_path), "--workers", "2"])
    assert code == 0, screen
    _assert_same_results(tmp_path, first_batch[0])


def test_the_python_api_builds_the_same_graph(first_batch, captures: dict[str, Path], cluster: Cluster) -> None:
    import dask
    from distributed import Client

    from batch import build_graph

    graphs = build_graph([read_capture(captures[n]) for n in GOOD], first_batch[0])
    stages = [sorted(key.split("-")[1] for key in graph.tasks) for graph in graphs]
    assert stages[0] == ["probe", "probe", "probe", "register", "solve"]  # ready tracks: no track tasks
    assert stages[1] == ["probe", "probe", "probe", "register", "solve", "track", "track", "track"]
    with Client(cluster.address, timeout="30s"):
        outcomes = dask.compute(*[graph.final for graph in graphs])
    assert [(o.capture, o.stage, o.status) for o in outcomes] == [(n, "solve", "skipped") for n in GOOD]


def test_offsets_naming_a_video_a_capture_lacks_fail_it_before_any_work(
    captures: dict[str, Path], tmp_path: Path
) -> None:
    code, screen = _batch([str(captures["walk"]), "--out", str(tmp_path), "--offsets", "cam0=0,cam9=0.1"])
    assert code == 1, screen
    entry = _state(tmp_path)["walk"]
    assert entry["status"] == "failed" and entry["stage"] == "read"
    assert "--offsets names video 'cam9', which is not among the videos" in entry["error"]
    code, screen = _batch([str(captures["walk"]), "--out", str(tmp_path), "--offsets", "cam0=0", "--synchronized"])
    assert code == 2 and "--synchronized and --offsets both given" in screen


def test_local_workers_leave_ctrl_c_to_the_batch() -> None:
    """Ctrl+C reaches the whole process group: the local workers ignore it (the batch stops them), a remote
    scheduler's workers are not touched. In a child process: a client leaves Dask's threads running, which keep
    this worker's later tests from forking."""
    code = (
        "import signal; from batch.graph import BatchOptions, connect\n"
        "with connect(BatchOptions(workers=1)) as client:\n"
        "    print(list(client.run(lambda: signal.getsignal(signal.SIGINT)).values()))\n"
    )
    repo = Path(__file__).resolve().parents[2]
    command = [sys.executable, "-c", code]
    out = subprocess.run(command, cwd=repo, capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[<Handlers.SIG_IGN: 1>]"
