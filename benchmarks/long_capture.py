"""Long captures: time, peak memory and accuracy of the solver for F = 700 ... 20,000 frames with P = 20 points,
with every frame of the other videos as a candidate (dense, the paper's dictionary) and with windowed candidate
dictionaries (reconstruct/solver/candidates.py; the default above SolverOptions.dense_limit frames).

    python benchmarks/long_capture.py [--sizes 700,2000,5000,20000] [--dense-max 2000] [--json OUT]

Data: complexknee 2022_01_0401 (100 Hz, 33.8 s; ../shared/data/mocap/lab/complexknee), 20 markers without gaps,
resampled to 120 Hz and played forward, backward, forward ... until F captures exist (the shared files are at most
34 s long; the reversal is a continuous motion that repeats poses, which the dictionaries must not confuse), while
the whole body wanders slowly about the room (up to 0.3 m; else passes k and k + 2 would be exact copies). The
paper's protocol: 4 static cameras, 30 Hz each, noise-free, cameras at 2.7 m. Each (size, mode) runs in a fresh
process with one BLAS thread, so that its peak resident memory (getrusage) is its own.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import require_mocap_dir, resample, solver_version

FILE = "lab/complexknee/2022_01_0401.c3d"
POINTS = 20
RATE_HZ = 120.0
WANDER_MM = 150.0
DISTANCE_MM = 2700.0
RESULT_PREFIX = "RESULT "


def long_motion(frames: int) -> tuple[np.ndarray, list[str]]:
    """(frames, POINTS, 3) mm at RATE_HZ, ping-pong over the file."""
    from reconstruct.outputs.mocap import read_mocap

    mocap = read_mocap(require_mocap_dir() / FILE)
    complete = np.flatnonzero(~mocap.missing().any(axis=0))
    if len(complete) < POINTS:
        raise SystemExit(f"{FILE}: only {len(complete)} markers without gaps")
    seconds = (mocap.num_frames - 1) / mocap.rate - 0.05
    clip = resample(mocap, RATE_HZ, 0.0, seconds)
    markers = complete[:POINTS]
    xyz = clip.xyz[:, markers]
    passes = [xyz if k % 2 == 0 else xyz[::-1][1:] for k in range(frames // len(xyz) + 2)]
    motion = np.concatenate(passes)[:frames]
    # The subject wanders slowly about the room (up to ~0.3 m): without it, passes k and k + 2 are exact copies and
    # every frame has several equally good matches 67 s apart, which no real capture has.
    t = np.arange(frames) / RATE_HZ
    wander = WANDER_MM * np.stack(
        [np.sin(2 * np.pi * t / 83.0), 1.0 - np.cos(2 * np.pi * t / 61.0), np.zeros_like(t)], axis=1
    )
    return motion + wander[:, None, :], [mocap.marker_names[m] for m in markers]


def long_problem(frames: int) -> tuple[Any, Any]:
    """(SimulatedCapture, Problem) of `long_motion(frames)`: the paper's protocol, cameras at DISTANCE_MM."""
    from reconstruct.inputs import build_problem
    from simulation.simulate import SimulationOptions, simulate_capture

    xyz, names = long_motion(frames)
    capture = simulate_capture(xyz, RATE_HZ, SimulationOptions(camera_distance_mm=DISTANCE_MM), marker_names=names)
    return capture, build_problem(capture.cameras, capture.tracks, point_names=names)


def child(frames: int, dense: bool) -> dict[str, Any]:
    from threadpoolctl import threadpool_limits

    from reconstruct.solver.alternation import SolverOptions, solve
    from reconstruct.stage import frame_points
    from simulation.evaluate import evaluate

    threadpool_limits(1)
    capture, problem = long_problem(frames)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    options = SolverOptions(dense_limit=10**9 if dense else 0)
    wall, cpu = time.perf_counter(), time.process_time()
    result = solve(problem, options)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    accuracy = evaluate(frame_points(problem, result), capture.truth)
    return {
        "frames": problem.num_frames,
        "points": problem.num_points,
        "mode": "dense" if dense else "windowed",
        "wall_s": wall,
        "cpu_s": cpu,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_mb": rss_before,
        "iterations": [s.iterations for s in result.stages],
        "timings": result.timings,
        "share_under": [float(s) for s in accuracy.share_under],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="700,2000,5000,20000")
    parser.add_argument("--dense-max", type=int, default=2000, help="largest F also solved with dense dictionaries")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per solve before it is abandoned")
    parser.add_argument("--child", nargs=2, metavar=("FRAMES", "DENSE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(RESULT_PREFIX + json.dumps(child(int(args.child[0]), args.child[1] == "1")), flush=True)
        return 0
    results = []
    for frames in (int(s) for s in args.sizes.split(",")):
        for dense in [True, False] if frames <= args.dense_max else [False]:
            try:
                out = subprocess.run(
                    [sys.executable, __file__, "--child", str(frames), "1" if dense else "0"],
                    capture_output=True,
                    text=True,
                    check=False,
                    timeout=args.timeout,
                )
            except subprocess.TimeoutExpired:
                print(f"F = {frames} {'dense' if dense else 'windowed'}: over {args.timeout:.0f} s, abandoned")
                continue
            lines = [line for line in out.stdout.splitlines() if line.startswith(RESULT_PREFIX)]
            if not lines:
                print(f"F = {frames} {'dense' if dense else 'windowed'} failed:\n{out.stderr[-2000:]}")
                continue
            results.append(json.loads(lines[-1][len(RESULT_PREFIX) :]))
            if args.json:
                args.json.write_text(json.dumps({"solver": solver_version(), "results": results}, indent=1))
    from reconstruct.solver.alternation import SolverOptions

    print(
        f"solver {solver_version()}; P = {POINTS}, 30 Hz per camera, noise-free, 1 BLAS thread, "
        f"{SolverOptions().workers} solver threads (SolverOptions.workers)"
    )
    print("| F | dictionary | wall s | CPU s | peak RSS MB | iterations | < 10 mm % | < 20 mm % |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        print(
            f"| {r['frames']} | {r['mode']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['peak_rss_mb']:.0f} | "
            f"{'+'.join(map(str, r['iterations']))} | {100 * r['share_under'][0]:.2f} | "
            f"{100 * r['share_under'][1]:.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
