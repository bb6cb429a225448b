"""The paper's protocol with no time information at all (issue 17): captures assigned to random cameras, no camera
twice in a row, and cameras.json without fps or frame times. Per mocap window the seed solve (`--refinement none`)
beside the default `dynrecon solve` (clocks checked, else per-frame times, else the seed), which path it took, which
times the free-time path used (`order`: the polished frame order's fixed times; `retimed`: free per-frame times) and
the first failing check.

    nice python benchmarks/no_times.py                       # first 6 windows, noise-free and 1 px + 20 % missing
    nice python benchmarks/no_times.py --windows hdm05,cmu-jumps --json /tmp/no_times.json
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from common import WINDOWS, CaptureSetting, load_window, simulate

from reconstruct.solver.alternation import SolverOptions, solve
from reconstruct.temporal import recover_and_refine

SETTINGS = {
    "clean": CaptureSetting(key="clean", label="30 Hz, noise-free"),
    "noisy": CaptureSetting(key="noisy", label="30 Hz, 1 px, 20 % missing", noise_px=1.0, miss=0.2),
}


def share(points: np.ndarray, truth: np.ndarray) -> float:
    error = np.linalg.norm(points - truth, axis=-1)
    return float(np.mean(error[np.isfinite(error)] < 10.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--windows", default=",".join(w.name for w in WINDOWS[:6]))
    parser.add_argument("--settings", default="clean,noisy")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    rows = []
    print(
        "| window | setting | seed < 10 mm | default < 10 mm | path | times | first failing check |"
        " seconds (seed + after) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in args.windows.split(","):
        window = next(w for w in WINDOWS if w.name == name)
        mocap = load_window(window)
        for key in args.settings.split(","):
            setting = SETTINGS[key]
            options = replace(
                setting.simulation_options(mocap, seed=WINDOWS.index(window), camera_distance_mm=None), times=False
            )
            capture, problem, _ = simulate(mocap, options)
            index = capture.truth.index()
            truth = np.stack(
                [
                    capture.truth.xyz[index[(v, int(f))]]
                    for v, f in zip(problem.frame_videos, problem.frames, strict=True)
                ]
            )
            started = time.perf_counter()
            seed = solve(problem, SolverOptions())  # what `dynrecon solve` runs
            middle = time.perf_counter()
            temporal = recover_and_refine(problem, seed)
            end = time.perf_counter()
            checks = temporal.report.get("checks", [])
            failed = next((c for c in checks if not c["passed"]), None)
            times = _free_times_source(temporal.report, checks)
            row = {
                "window": name,
                "setting": key,
                "seed": share(seed.points, truth),
                "default": share(temporal.points, truth),
                "path": temporal.report.get("path"),
                "times": times,
                "failed": failed["name"] if failed else None,
                "failed_value": failed["value"] if failed else None,
                "seconds_seed": middle - started,
                "seconds_after": end - middle,
            }
            rows.append(row)
            check = f"{row['failed']} {row['failed_value']:.3g}" if failed else "-"
            print(
                f"| {name} | {setting.label} | {100 * row['seed']:.2f} % | {100 * row['default']:.2f} % | "
                f"{row['path']} | {times} | {check} | {row['seconds_seed']:.0f} + {row['seconds_after']:.0f} |",
                flush=True,
            )
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))
    for key in args.settings.split(","):
        subset = [r for r in rows if r["setting"] == key]
        if subset:
            worse = sum(r["default"] < r["seed"] - 1e-9 for r in subset)
            print(
                f"\n{SETTINGS[key].label}: mean seed {100 * np.mean([r['seed'] for r in subset]):.2f} %, default "
                f"{100 * np.mean([r['default'] for r in subset]):.2f} %, default below the seed on {worse} of "
                f"{len(subset)} windows"
            )


def _free_times_source(report: dict[str, Any], checks: list[dict[str, Any]]) -> str:
    """`order` or `retimed` on the free-time path, else `-`."""
    if report.get("path") != "free_times":
        return "-"
    source = report.get("free_times_source")
    if isinstance(source, str):
        return source
    return "order" if any(c["name"] == "order_fit" for c in checks) else "retimed"


if __name__ == "__main__":
    main()
