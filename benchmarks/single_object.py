"""One moving point (a drone, a ball, a bat): the whole `dynrecon solve` on the flight simulation, against
triangulation with the true times.

    python benchmarks/single_object.py [--durations 5,20,60,150] [--seed 1] [--cases DIR] [--json OUT]

Per flight duration: `dynrecon simulate --mode flight` (5 phones at 24-60 fps on their own clocks, 30-100 m away,
1.5 px noise, 3 % false detections; about 169 captures per second, so 150 s gives F = 25,000), then
`dynrecon solve --no-recording` as a subprocess (the process time counts imports and file reading; its CPU time
counts all its threads, for a machine shared with other jobs). The first table gives the process time, report.json's
path (`tracks`: clocks from the tracks, no self-expressive solve) and the median 3D error (mm) of the solve's
trajectory against two references computed on the same simulation with the TRUE capture times:
- `nearest`: each observation triangulated with the nearest-in-time observation of every other video
  (`reconstruct.tracks_path.start_points`, what a tool that assumes synchronized frames would do at best);
- `spline`: the refinement's spline through all rays on the true times (`reconstruct.trajectory.refine` from
  `nearest`), the best the solve can reach with perfect clocks.

The second table gives every stage of report.json's `timings`.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from reconstruct.inputs import build_problem_checked  # noqa: E402
from reconstruct.solver.problem import Problem  # noqa: E402
from reconstruct.tracks_path import start_points  # noqa: E402
from reconstruct.trajectory import refine  # noqa: E402
from sfm.cameras import read_cameras  # noqa: E402
from tracking.tracks import read_tracks  # noqa: E402


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def dynrecon(args: list[str], timeout: float) -> tuple[float, float]:
    """Runs `dynrecon ARGS` in a subprocess: (wall s, CPU s of the process, all its threads)."""
    start, cpu = time.perf_counter(), _children_cpu()
    subprocess.run([sys.executable, "-m", "dynrecon", "-q", *args], check=True, timeout=timeout, cwd=ROOT)
    return time.perf_counter() - start, _children_cpu() - cpu


def truth_of(folder: Path, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(F,) true capture times and (F, 3) true positions of the problem's frames, from truth.csv."""
    rows = {(r["video"], int(r["frame"])): r for r in csv.DictReader((folder / "truth.csv").open())}
    keys = [rows[(v, int(f))] for v, f in zip(problem.frame_videos, problem.frames, strict=True)]
    times = np.array([float(r["time"]) for r in keys])
    xyz = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in keys])
    return times, xyz


def median_error(points: np.ndarray, truth: np.ndarray) -> float:
    """Median 3D distance (mm) over the frames with a point."""
    error = np.linalg.norm(points - truth, axis=-1)
    return float(np.median(error[np.isfinite(error)]))


def references(folder: Path) -> dict[str, float]:
    """Median errors (mm) of triangulation with the true times: nearest partners, and the spline on them."""
    problem, _ = build_problem_checked(read_cameras(folder / "cameras.json"), read_tracks(folder / "tracks.csv"))
    times, truth = truth_of(folder, problem)
    nearest = start_points(problem, times)
    spline = refine(problem, nearest, times).points
    return {"nearest_mm": median_error(nearest[:, 0], truth), "spline_mm": median_error(spline[:, 0], truth)}


def solve_case(folder: Path, timeout: float) -> dict[str, object]:
    cmd = ["solve", "--cameras", str(folder / "cameras.json"), "--tracks", str(folder / "tracks.csv")]
    try:
        seconds, cpu = dynrecon([*cmd, "--out", str(folder / "out"), "--no-recording"], timeout)
    except subprocess.TimeoutExpired:
        return {"process_s": float("inf"), "path": "timeout"}
    report = json.loads((folder / "out" / "report.json").read_text())
    evaluate = ["evaluate", str(folder / "out"), "--truth", str(folder / "truth.csv"), "--json"]
    scored = subprocess.run(
        [sys.executable, "-m", "dynrecon", *evaluate],
        check=True,
        capture_output=True,
        text=True,
        cwd=ROOT,
    ).stdout
    return {
        "process_s": seconds,
        "cpu_s": cpu,
        "F": report["size"]["frames"],
        "path": report["temporal"].get("path"),
        "timings": report["timings"],
        "median_mm": json.loads(scored)["median"],
    }


def print_tables(rows: dict[str, dict[str, object]]) -> None:
    """The summary table, then every report.json timing (s) per flight."""
    print("\n| flight | F | process s | process CPU s | path | median mm | true times: nearest | spline |")
    print("|---|---|---|---|---|---|---|---|")
    for duration, r in rows.items():
        print(
            f"| {duration} s | {r.get('F', '')} | {r['process_s']:.1f} | {r.get('cpu_s', float('nan')):.1f} | "
            f"{r['path']} | {r.get('median_mm', float('nan')):.0f} | {r['nearest_mm']:.0f} | {r['spline_mm']:.0f} |"
        )
    timings = {d: t for d, r in rows.items() if isinstance(t := r.get("timings"), dict)}
    stages = list(dict.fromkeys(k for t in timings.values() for k in t))
    print(f"\n| flight | {' | '.join(stages)} |")
    print(f"|---|{'---|' * len(stages)}")
    for duration, t in timings.items():
        print(f"| {duration} s | {' | '.join(f'{t[k]:.2f}' if k in t else '' for k in stages)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--durations", default="5,20", help="flight durations in s, comma-separated")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=1200.0, help="seconds per solve")
    parser.add_argument("--cases", type=Path, help="keep the simulated flights here and reuse them")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    rows: dict[str, dict[str, object]] = {}
    with contextlib.ExitStack() as stack:
        base = args.cases or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        for duration in args.durations.split(","):
            folder = base / f"flight-{duration}s-seed{args.seed}"
            if not (folder / "tracks.csv").exists():
                sim = ["simulate", "--mode", "flight", "--duration", duration, "--seed", str(args.seed)]
                dynrecon([*sim, "--out", str(folder)], 600)
            rows[duration] = {**solve_case(folder, args.timeout), **references(folder)}
            print(duration, json.dumps(rows[duration]), flush=True)
    print_tables(rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
