"""Reproduce the seed paper's three accuracy tables on the shared motion capture (../shared/data/mocap).

    python benchmarks/paper_tables.py [--windows 6] [--rows frame,noise,missing] [--length 300] [--jobs 1]
                                      [--per-window] [--json OUT]
    python benchmarks/paper_tables.py --from-json OUT [OUT2 ...] [--per-window]   # tables of earlier runs

Protocol (the paper's, via simulation.simulate): 4 static virtual cameras, each capture time seen by one camera.
Rows: 30 / 15 / 7.5 Hz per camera (every 1st / 2nd / 4th sample of 120 Hz motion), 30 Hz with unconstrained camera
assignment, Gaussian pixel noise sigma 1..5 px and 10..50 % missing observations (both at 30 Hz). Columns: share of
points whose error is under 10, 20, 30, 40, 50, 100 mm, averaged over the windows (each window weighs the same).
"init" rows score the initialization alone (nearly-intersecting ray bundles, missing points interpolated), the
solver's starting point.

Windows: a fixed list (common.WINDOWS: HDM05, CMU, gait-lab squats, running, drop jump, walking, ...), 300 captures
at 120 Hz (2.5 s) each unless the file is shorter; files whose rate is not a multiple of 120 Hz are resampled to
120 Hz by a cubic spline. Seeds are fixed (window k uses seed k), so reruns give the same numbers.

Runtime: one solve of 300 frames x ~45 points takes ~20-40 s on one core (fewer frames at 15 / 7.5 Hz), so the
default run (6 windows x 14 rows = 84 solves) takes 1-2 hours on one core (the missing-data rows take
30-600 s per solve); `--jobs N` runs N windows'
solves in parallel processes (each with one BLAS thread). Default 1 job: the machine is shared.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy: one BLAS thread per process

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (
    PAPER,
    WINDOWS,
    CaptureSetting,
    Window,
    load_window,
    percent_row,
    require_mocap_dir,
    simulate,
    solve_and_score,
    solver_version,
    threshold_header,
)

from reconstruct.outputs.mocap import Mocap

log = logging.getLogger("paper_tables")


@dataclass(frozen=True, kw_only=True)
class Row(CaptureSetting):
    """A row of the paper's tables; `key` is also the key of common.PAPER."""

    group: str  # frame | noise | missing


ROWS: tuple[Row, ...] = (
    Row(key="30Hz", group="frame", label="30 Hz per camera"),
    Row(key="15Hz", group="frame", label="15 Hz", per_camera_hz=15.0),
    Row(key="7.5Hz", group="frame", label="7.5 Hz", per_camera_hz=7.5),
    Row(key="30Hz-unconstrained", group="frame", label="30 Hz, unconstrained assignment", unconstrained=True),
    *(Row(key=f"noise{s}", group="noise", label=f"noise sigma {s} px", noise_px=float(s)) for s in range(1, 6)),
    *(Row(key=f"missing{m}", group="missing", label=f"missing {m} %", miss=m / 100) for m in range(10, 60, 10)),
)
GROUPS = ("frame", "noise", "missing")
TITLES = {
    "frame": "Table 1: frame rate per camera (noise-free, nothing missing)",
    "noise": "Table 2: Gaussian pixel noise (30 Hz per camera)",
    "missing": "Table 3: missing observations (30 Hz per camera, noise-free)",
}


@dataclass(kw_only=True)
class Task:
    window_index: int
    row: Row
    length: int
    distance_mm: float | None = None  # fixed camera distance (the paper's 2.7 m), None = push back until visible


@dataclass(kw_only=True)
class Outcome:
    window: str
    row: str
    result: dict[str, Any] = field(default_factory=dict)
    error: str | None = None


def _limit_threads() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


@functools.lru_cache(maxsize=4)
def _window_mocap(window: Window, length: int) -> Mocap:
    seconds = min(window.seconds, length / 120.0)
    return load_window(replace(window, seconds=seconds))


def run_task(task: Task) -> Outcome:
    """Simulate, solve and score one (window, row); runs in a worker process."""
    window = WINDOWS[task.window_index]
    row = task.row
    outcome = Outcome(window=window.name, row=row.key)
    try:
        mocap = _window_mocap(window, task.length)
        options = row.simulation_options(mocap, task.window_index, task.distance_mm)
        capture, problem, distance = simulate(mocap, options)
        run, _ = solve_and_score(capture, problem)
        outcome.result = {**run.as_dict(), "camera_distance_mm": distance}
    except Exception as error:  # one failing window must not lose the others' hours of work
        log.exception("%s / %s failed", window.name, row.key)
        outcome.error = f"{type(error).__name__}: {error}"
    return outcome


def parse_windows(text: str) -> list[int]:
    if text.isdigit():
        count = int(text)
        if not 1 <= count <= len(WINDOWS):
            raise SystemExit(f"--windows: between 1 and {len(WINDOWS)}")
        return list(range(count))
    names = [w.name for w in WINDOWS]
    chosen = []
    for name in text.split(","):
        if name not in names:
            raise SystemExit(f"--windows: unknown window {name!r}; known: {', '.join(names)}")
        chosen.append(names.index(name))
    return chosen


def parse_rows(text: str) -> list[Row]:
    chosen: list[Row] = []
    for part in text.split(","):
        part = part.strip()
        if part in GROUPS:
            chosen.extend(r for r in ROWS if r.group == part)
        elif part in {r.key for r in ROWS}:
            chosen.extend(r for r in ROWS if r.key == part)
        else:
            raise SystemExit(
                f"--rows: unknown {part!r}; give groups ({', '.join(GROUPS)}) or row keys "
                f"({', '.join(r.key for r in ROWS)})"
            )
    return list(dict.fromkeys(chosen))


def print_tables(outcomes: list[Outcome], rows: list[Row], window_indices: list[int], per_window: bool) -> None:
    by_key: dict[tuple[str, str], Outcome] = {(o.window, o.row): o for o in outcomes}
    names = [WINDOWS[i].name for i in window_indices]
    for group in GROUPS:
        group_rows = [r for r in rows if r.group == group]
        if group == "missing" and group_rows and any(r.key == "30Hz" for r in rows):
            group_rows = [Row(key="30Hz", group="missing", label="missing 0 % (= 30 Hz row)"), *group_rows]
        if not group_rows:
            continue
        print(f"\n### {TITLES[group]}\n")
        print(threshold_header("setting", extra="windows, median error, s/solve"))
        for row in group_rows:
            done = [by_key[(n, row.key)] for n in names if (n, row.key) in by_key and by_key[(n, row.key)].result]
            paper_key = "missing0" if row.label.startswith("missing 0") else row.key
            if done:
                shares = np.mean([o.result["shares"] for o in done], axis=0)
                init = np.mean([o.result["init_shares"] for o in done], axis=0)
                median = float(np.median([o.result["median_mm"] for o in done]))
                seconds = float(np.mean([o.result["seconds"] for o in done]))
                failed = sum(1 for n in names if (n, row.key) in by_key and by_key[(n, row.key)].error)
                note = f" {len(done)}{f' ({failed} failed)' if failed else ''}, {median:.2f} mm, {seconds:.0f} s |"
                print(percent_row(f"{row.label}: ours", shares, note))
                print(percent_row(f"{row.label}: paper", PAPER[paper_key], " |"))
                print(percent_row(f"{row.label}: init only", init, " |"))
            else:
                print(percent_row(f"{row.label}: paper", PAPER[paper_key], " (not run) |"))
            if per_window:
                for name in names:
                    outcome = by_key.get((name, row.key))
                    if outcome is None:
                        continue
                    if outcome.error:
                        print(f"| &nbsp;&nbsp;{name} | failed: {outcome.error} |")
                        continue
                    r = outcome.result
                    distance = r.get("camera_distance_mm")
                    where = f"cameras at {distance / 1000:.1f} m, " if distance else ""
                    print(
                        percent_row(
                            f"&nbsp;&nbsp;{name}",
                            r["shares"],
                            f" F={r['frames']} P={r['points']}, {where}{r['median_mm']:.2f} mm, "
                            f"{r['seconds']:.0f} s, init <10 mm {100 * r['init_shares'][0]:.1f} % |",
                        )
                    )


def reprint(paths: list[Path], rows: list[Row], per_window: bool) -> int:
    """Tables of earlier runs: the windows and rows found in the files, in list order, restricted to `rows`."""
    merged: dict[tuple[str, str], Outcome] = {}
    for path in paths:
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise SystemExit(f"{path}: not a paper_tables --json file ({error})") from None
        for item in data.get("results", []):
            outcome = Outcome(
                window=item["window"], row=item["row"], result=item.get("result") or {}, error=item.get("error")
            )
            merged[(outcome.window, outcome.row)] = outcome
    names = [w.name for w in WINDOWS]
    window_indices = sorted({names.index(w) for w, _ in merged if w in names})
    present = {r for _, r in merged}
    for path in paths:
        print(f"{path}: solver {json.loads(path.read_text()).get('solver', 'not recorded')}")
    print("Windows: " + ", ".join(f"{i}. {names[i]} ({WINDOWS[i].path})" for i in window_indices))
    print_tables(list(merged.values()), [r for r in rows if r.key in present], window_indices, per_window)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--windows",
        default="6",
        help=f"how many windows of the fixed list (1-{len(WINDOWS)}), or comma-separated names",
    )
    parser.add_argument(
        "--rows", default="frame,noise,missing", help="groups (frame, noise, missing) and/or row keys, comma-separated"
    )
    parser.add_argument("--length", type=int, default=300, help="captures per window at 120 Hz (default 300)")
    parser.add_argument(
        "--distance",
        type=float,
        default=None,
        metavar="MM",
        help="fixed camera distance in mm, as in the paper's protocol (2700); default: cameras at "
        "twice the motion's extent, moved back until every point is inside the images",
    )
    parser.add_argument("--jobs", type=int, default=1, help="parallel worker processes (default 1)")
    parser.add_argument("--per-window", action="store_true", help="also print one line per window")
    parser.add_argument("--json", type=Path, help="write every result (updated after each solve) to this file")
    parser.add_argument(
        "--from-json",
        type=Path,
        nargs="+",
        metavar="JSON",
        help="solve nothing: print the tables of earlier --json files (merged; later files win)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    for noisy in ("reconstruct", "common"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    window_indices = parse_windows(args.windows)
    rows = parse_rows(args.rows)
    if args.from_json:
        return reprint(args.from_json, rows, args.per_window)
    require_mocap_dir()
    if args.length < 20:
        raise SystemExit("--length: at least 20 captures")

    version = solver_version()
    print(f"solver: {version}")
    print("Windows (4 cameras; 300 captures at 120 Hz = 2.5 s unless noted; seed = list position):")
    for i in window_indices:
        w = WINDOWS[i]
        print(f"  {i}. {w.name}: {w.path}, {w.motion}, from {w.start_s:g} s, {min(w.seconds, args.length / 120):.2f} s")
    print(
        f"Rows: {', '.join(r.key for r in rows)}; {len(window_indices) * len(rows)} solves, {args.jobs} job(s)",
        flush=True,
    )

    tasks = [
        Task(window_index=i, row=r, length=args.length, distance_mm=args.distance) for r in rows for i in window_indices
    ]
    outcomes: list[Outcome] = []
    started = time.perf_counter()

    def record(outcome: Outcome) -> None:
        outcomes.append(outcome)
        if outcome.error:
            log.info(
                "[%d/%d] %s / %s FAILED: %s", len(outcomes), len(tasks), outcome.window, outcome.row, outcome.error
            )
        else:
            r = outcome.result
            log.info(
                "[%d/%d] %s / %s: <10 mm %.2f %% (init %.2f %%), F=%d, %.0f s",
                len(outcomes),
                len(tasks),
                outcome.window,
                outcome.row,
                100 * r["shares"][0],
                100 * r["init_shares"][0],
                r["frames"],
                r["seconds"],
            )
        if args.json:
            args.json.write_text(
                json.dumps(
                    {
                        "solver": version,
                        "windows": [WINDOWS[i].__dict__ for i in window_indices],
                        "length": args.length,
                        "paper": PAPER,
                        "results": [o.__dict__ for o in outcomes],
                    },
                    indent=1,
                )
                + "\n"
            )

    if args.jobs <= 1:
        _limit_threads()
        logging.getLogger().setLevel(logging.INFO)
        for task in tasks:
            record(run_task(task))
    else:
        with ProcessPoolExecutor(max_workers=args.jobs, initializer=_limit_threads) as pool:
            futures = [pool.submit(run_task, task) for task in tasks]
            for future in as_completed(futures):
                record(future.result())
    print_tables(outcomes, rows, window_indices, args.per_window)
    print(f"\n{len(outcomes)} solves in {time.perf_counter() - started:.0f} s wall")
    return 1 if any(o.error for o in outcomes) else 0


if __name__ == "__main__":
    sys.exit(main())
