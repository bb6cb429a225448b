"""`dynrecon batch` throughput: captures per minute with 1 and 2 Dask workers, and the per-video speed-up of tracking
and of SfM registration.

Four tables:

1. Throughput: a batch of small simulated captures (calibrated static phones, labels tracked per video, the full
   solve) on a LocalCluster of 1 worker and of 2 workers, one thread each. The workers are started and warmed up
   (stage modules imported) before the clock starts, as on a cluster that stays up; every run writes a fresh
   folder. Runs alternate 1, 2, 1, 2, ...; the table gives the median.
2. Per-video tracking inside one capture: the same capture's tracking as the pipeline's serial stage (one process,
   the videos one after the other) and as the batch's per-video tasks on 1 and 2 workers.
3. Per-stage seconds of one real capture (the embedded video sample: SfM registration, tracking, solve) through the
   batch, for the season estimate in docs/scaling.md (`--real`; skipped when the sample is absent).

4. Per-video SfM registration inside one capture (`--register`): the synthetic room's 3 moving cameras registered
   as the pipeline's serial `register` stage (one process) and as the batch's per-video tasks (plan, extract,
   localize per video; map and the finish per capture) on 1 and 2 workers; COLMAP on one thread everywhere.

    python benchmarks/batch_throughput.py [--captures 6] [--repeats 3] [--real] [--register] [--skip-throughput]
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("TQDM_DISABLE", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import psutil  # noqa: E402
from distributed import Client, LocalCluster  # noqa: E402

from batch.capture import read_capture  # noqa: E402
from batch.graph import BatchOptions, build_graph, local_cluster, run_batch  # noqa: E402
from batch.state import CaptureStatus  # noqa: E402
from batch.synthetic import Inputs, SimulatedCaptureOptions, simulated_capture  # noqa: E402
from dynrecon.pipeline import PipelineOptions, Stages, default_register  # noqa: E402
from sfm.synthetic.demo import render_demo, three_cameras  # noqa: E402
from tracking.options import TrackOptions  # noqa: E402
from tracking.stage import run as track_run  # noqa: E402

SAMPLE = ROOT / "data_samples" / "video_sample"


def _cluster(workers: int) -> tuple[LocalCluster, Client]:
    cluster = local_cluster(workers)
    client = Client(cluster)
    client.run(importlib.import_module, "batch.tasks")  # warm: the stage modules load once per worker
    return cluster, client


def _cpu_seconds() -> float:
    """CPU seconds of this worker process and its finished children (COLMAP runs in child processes)."""
    times = psutil.Process().cpu_times()
    return float(times.user + times.system + times.children_user + times.children_system)


def _workers_cpu(client: Client) -> float:
    return sum(client.run(_cpu_seconds).values())


@dataclass
class Run:
    wall: float  # seconds of the whole batch
    cpu: float  # CPU seconds the workers used
    busy: float  # task seconds / (workers x wall): 1 when no worker ever waits for work


def throughput(folders: list[Path], work: Path, repeats: int) -> dict[int, list[Run]]:
    runs: dict[int, list[Run]] = {1: [], 2: []}
    clusters = {n: _cluster(n) for n in (1, 2)}
    try:
        for repeat in range(repeats):
            for workers in (1, 2):
                client = clusters[workers][1]
                out = work / f"throughput-{workers}-{repeat}"
                options = BatchOptions(scheduler=clusters[workers][0].scheduler_address, progress=False)
                cpu = _workers_cpu(client)
                started = time.perf_counter()
                report = run_batch(folders, out, options)
                wall = time.perf_counter() - started
                assert not report.failed, report.failed
                tasks = sum(sum(s.seconds.values()) for s in report.captures.values())
                runs[workers].append(Run(wall=wall, cpu=_workers_cpu(client) - cpu, busy=tasks / (workers * wall)))
                shutil.rmtree(out)
                run = runs[workers][-1]
                print(
                    f"  run {repeat + 1}, {workers} worker(s): {run.wall:.1f} s, {run.cpu:.1f} CPU s, "
                    f"busy {100 * run.busy:.0f} %, load {os.getloadavg()[0]:.1f}",
                    flush=True,
                )
    finally:
        for cluster, client in clusters.values():
            client.close()
            cluster.close()
    return runs


def per_video(folder: Path, work: Path, repeats: int) -> dict[str, list[Run]]:
    """One capture's tracking: serial in this process, and as per-video tasks on 1 and 2 workers."""
    capture = read_capture(folder)
    runs: dict[str, list[Run]] = {"serial": [], "1": [], "2": []}
    clusters = {n: _cluster(n) for n in (1, 2)}
    try:
        for repeat in range(repeats):
            serial = work / f"serial-{repeat}"
            serial.mkdir()
            shutil.copyfile(folder / "labels.csv", serial / "labels.csv")
            cpu, started = time.process_time(), time.perf_counter()
            track_run(serial, serial / "tracks.csv", TrackOptions(), videos={p.stem: p for p in capture.videos})
            wall = time.perf_counter() - started
            runs["serial"].append(Run(wall=wall, cpu=time.process_time() - cpu, busy=1.0))
            for workers in (1, 2):
                client = clusters[workers][1]
                graph = build_graph([capture], work / f"tasks-{workers}-{repeat}", BatchOptions())[0]
                probes = [d for k, d in graph.tasks.items() if k.startswith("dynrecon-probe-")]
                client.compute(probes, sync=True)  # the probes first: the timed part is the tracking alone
                tracks = [d for k, d in graph.tasks.items() if k.startswith("dynrecon-track-")]
                cpu, started = _workers_cpu(client), time.perf_counter()
                outcomes = client.compute(tracks, sync=True)
                wall = time.perf_counter() - started
                assert all(o.status == "done" for o in outcomes), outcomes
                busy = sum(o.seconds for o in outcomes) / (workers * wall)
                runs[str(workers)].append(Run(wall=wall, cpu=_workers_cpu(client) - cpu, busy=busy))
            print(
                f"  run {repeat + 1}: "
                + ", ".join(f"{k} {v[-1].wall:.1f} s ({v[-1].cpu:.1f} CPU s)" for k, v in runs.items())
                + f", load {os.getloadavg()[0]:.1f}",
                flush=True,
            )
    finally:
        for cluster, client in clusters.values():
            client.close()
            cluster.close()
    return runs


def _own_cpu_seconds() -> float:
    times = psutil.Process().cpu_times()
    return float(times.user + times.system + times.children_user + times.children_system)


def per_video_register(folder: Path, work: Path, repeats: int, frames: tuple[int, ...]) -> dict[str, list[Run]]:
    """One capture's SfM registration: the serial stage in this process, and the per-video tasks on 1 and 2
    workers (the probes first: the timed part is registration alone)."""
    capture = read_capture(folder)
    register = replace(default_register(), long_side=480, max_frames=max(frames) // 2, max_features=1500)
    options = PipelineOptions(register=replace(register, num_threads=1))
    runs: dict[str, list[Run]] = {"serial": [], "1": [], "2": []}
    clusters = {n: _cluster(n) for n in (1, 2)}
    try:
        for repeat in range(repeats):
            cpu, started = _own_cpu_seconds(), time.perf_counter()
            Stages(capture.videos, work / f"reg-serial-{repeat}", options).register()
            runs["serial"].append(Run(wall=time.perf_counter() - started, cpu=_own_cpu_seconds() - cpu, busy=1.0))
            for workers in (1, 2):
                client = clusters[workers][1]
                graph = build_graph([capture], work / f"reg-tasks-{workers}-{repeat}", BatchOptions(pipeline=options))[
                    0
                ]
                probes = [d for k, d in graph.tasks.items() if k.startswith("dynrecon-probe-")]
                client.compute(probes, sync=True)
                final = next(d for k, d in graph.tasks.items() if k.startswith("dynrecon-register-"))
                cpu, started = _workers_cpu(client), time.perf_counter()
                outcome = client.compute(final, sync=True)
                wall = time.perf_counter() - started
                assert outcome.status == "done", outcome
                runs[str(workers)].append(Run(wall=wall, cpu=_workers_cpu(client) - cpu, busy=1.0))
            print(
                f"  run {repeat + 1}: "
                + ", ".join(f"{k} {v[-1].wall:.1f} s ({v[-1].cpu:.1f} CPU s)" for k, v in runs.items())
                + f", load {os.getloadavg()[0]:.1f}",
                flush=True,
            )
    finally:
        for cluster, client in clusters.values():
            client.close()
            cluster.close()
    return runs


def real_capture(work: Path) -> dict[str, object] | None:
    """The video sample through the batch on one worker: its per-stage seconds from batch.json."""
    if not (SAMPLE / "cam0.mp4").is_file():
        return None
    folder = work / "video_sample"
    folder.mkdir()
    for name in ("cam0.mp4", "cam1.mp4", "cam2.mp4", "labels.csv"):
        shutil.copyfile(SAMPLE / name, folder / name)
    shutil.copyfile(SAMPLE / "walker_skeleton.json", folder / "skeleton.json")
    from dynrecon.demo import pipeline_options

    options = BatchOptions(pipeline=pipeline_options(SAMPLE), workers=1, progress=False)
    started = time.perf_counter()
    report = run_batch([folder], work / "real", options)
    status = report.captures["video_sample"]
    return {"wall": time.perf_counter() - started, "status": status}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--real", action="store_true", help="also the per-stage seconds of the video sample")
    parser.add_argument("--register", action="store_true", help="also the per-video speed-up of SfM registration")
    parser.add_argument("--skip-throughput", action="store_true", help="leave out tables 1 and 2")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("distributed").setLevel(logging.ERROR)
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the start")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if not args.skip_throughput:
            throughput_tables(work, args.captures, args.repeats)
        if args.register:
            register_table(work, args.repeats)
        if args.real:
            real_table(work)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


def register_table(work: Path, repeats: int) -> None:
    frames = (24, 20, 16)
    folder = work / "room"
    render_demo(folder, three_cameras(480, 360, frames=frames))
    print(f"\n4. per-video SfM registration: the synthetic room, 3 moving cameras x {frames} frames at 480 x 360")
    runs = per_video_register(folder, work, repeats, frames)
    serial = statistics.median(r.wall for r in runs["serial"])
    print("\n| registration | wall, s (median) | speed-up vs serial | CPU s | cores obtained |")
    print("|---|---|---|---|---|")
    for name, label in (
        ("serial", "pipeline's serial stage (one process)"),
        ("1", "per-video tasks, 1 worker"),
        ("2", "per-video tasks, 2 workers"),
    ):
        wall = statistics.median(r.wall for r in runs[name])
        cpu = statistics.median(r.cpu for r in runs[name])
        cores = statistics.median(r.cpu / r.wall for r in runs[name])
        print(f"| {label} | {wall:.2f} | {serial / wall:.2f}x | {cpu:.1f} | {cores:.2f} |")


def throughput_tables(work: Path, captures: int, repeats: int) -> None:
    folders = [
        simulated_capture(
            work / f"capture{i}", SimulatedCaptureOptions(seed=i, inputs=Inputs.LABELS, points=6, seconds=1.5)
        )
        for i in range(captures)
    ]
    print(f"\n1. throughput: {captures} captures (3 phones, 6 points, 1.5 s, labels tracked per video)")
    runs = throughput(folders, work, repeats)
    one = statistics.median(r.wall for r in runs[1])
    print(
        "\n| workers | batch wall, s (median) | captures / min | speed-up | CPU s per capture | cores obtained "
        "| workers busy |"
    )
    print("|---|---|---|---|---|---|---|")
    for workers in (1, 2):
        wall = statistics.median(r.wall for r in runs[workers])
        cpu = statistics.median(r.cpu for r in runs[workers]) / captures
        cores = statistics.median(r.cpu / r.wall for r in runs[workers])
        busy = statistics.median(r.busy for r in runs[workers])
        print(
            f"| {workers} | {wall:.1f} | {60 * captures / wall:.1f} | {one / wall:.2f}x | {cpu:.1f} | "
            f"{cores:.2f} | {100 * busy:.0f} % |"
        )

    long_capture = simulated_capture(
        work / "long",
        SimulatedCaptureOptions(
            seed=7, inputs=Inputs.LABELS, points=12, seconds=8.0, fps=(30.0, 30.0, 30.0, 30.0), image_size=640
        ),
    )
    print("\n2. per-video tracking: one capture, 4 phones x 240 frames at 640 px, 12 points, labels every 4th")
    video_runs = per_video(long_capture, work, repeats)
    serial = statistics.median(r.wall for r in video_runs["serial"])
    print("\n| tracking | wall, s (median) | speed-up vs serial | CPU s | cores obtained |")
    print("|---|---|---|---|---|")
    for name, label in (
        ("serial", "pipeline's serial stage (one process)"),
        ("1", "per-video tasks, 1 worker"),
        ("2", "per-video tasks, 2 workers"),
    ):
        wall = statistics.median(r.wall for r in video_runs[name])
        cpu = statistics.median(r.cpu for r in video_runs[name])
        cores = statistics.median(r.cpu / r.wall for r in video_runs[name])
        print(f"| {label} | {wall:.2f} | {serial / wall:.2f}x | {cpu:.1f} | {cores:.2f} |")


def real_table(work: Path) -> None:
    real = real_capture(work)
    if real is None:
        print("\n3. real capture: data_samples/video_sample is not generated; skipped")
    else:
        status = real["status"]
        assert isinstance(status, CaptureStatus)
        print(f"\n3. the video sample through the batch, 1 worker: {real['wall']:.1f} s wall, {status.status}")
        print("\n| stage | seconds |")
        print("|---|---|")
        for stage, value in status.seconds.items():
            print(f"| batch {stage} | {value:.1f} |")
        for stage, seconds in status.pipeline.items():
            print(f"| pipeline {stage} | {'skipped' if seconds is None else f'{seconds:.1f}'} |")


if __name__ == "__main__":
    main()
