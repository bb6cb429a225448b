"""Clock recovery against ground truth: phone captures of real mocap and the single-drone flight scene.

Each row: simulate (simulation.phones / simulation.flight, known clocks and per-frame capture times),
solve, `estimate_clocks`, then compare every frame's global time with its true capture time. The estimate's gauge is
its reference video (offset 0, rate 1); the truth's is the scene start, so estimates are mapped through the
reference video's true clock (global_true = offset_ref + rate_ref * global_est) before scoring; jitter on the
reference's frames is then part of the error, as it is for every frame (CFR timestamps do not show it).

Columns: median |time error| in ms and as a fraction of the fastest camera's frame period (target < 0.25), p90,
calibration (share of frames whose error is within 2 reported std), the method per video, the median error of
the links of W alone (when they clock every video), CPU seconds of estimate_clocks and wall seconds of the solve.

Phones: CMU 01_01 jumps, 4 s, 41 markers, handheld, 1 px, offsets 0-1 s, +-50 ppm, 2 ms CFR jitter (the jitter
alone is the floor of any clock). Flight (tracks alone): 12 s, 1 drone point, 5 handheld phones 30-100 m away,
1.5 px, 3 % false detections, +-50 ppm, 2 ms jitter; scored with --max-iterations 0 (W's links of a single far point
do not clock anything; the search decides there either way).
Target: median < 0.25 of the fastest frame period. Results: docs/measurements.md.

    python benchmarks/clocks.py                       # phones (3 seeds) + flight (2 seeds)
    python benchmarks/clocks.py --scenes flight --seeds 0,1,2 --search always --json /tmp/clocks.json
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pickle
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_NUM_THREADS", "1")

from common import WINDOWS, load_window, solver_version  # noqa: E402

from reconstruct.clocks.estimate import ClockModel, ClockOptions, SearchMode, estimate_clocks  # noqa: E402
from reconstruct.inputs import build_problem  # noqa: E402
from reconstruct.solver.alternation import SolverOptions, solve  # noqa: E402
from simulation.flight import FlightOptions, simulate_flight  # noqa: E402
from simulation.phones import PhoneCaptureOptions, simulate_phones  # noqa: E402

log = logging.getLogger("benchmarks.clocks")

PHONE_WINDOW = "cmu-jumps"


def phone_capture(seed: int, seconds: float) -> tuple[Any, Any]:
    """4 handheld phones (30, 25, 59.94, 24 fps), starts within 1 s, +-50 ppm drift, 2 ms CFR jitter, 1 px."""
    window = next(w for w in WINDOWS if w.name == PHONE_WINDOW)
    mocap = load_window(replace(window, seconds=seconds))
    return simulate_phones(
        mocap,
        PhoneCaptureOptions(
            cameras=4, handheld=True, noise_px=1.0, offset_s=(0.0, 1.0), drift_ppm=50.0, jitter_ms=2.0, seed=seed
        ),
    )


def flight_capture(seed: int, seconds: float) -> tuple[Any, Any]:
    """The flight defaults (5 handheld phones 30-100 m away, 1.5 px, 3 % false detections) + drift and jitter."""
    capture, record, _ = simulate_flight(FlightOptions(seed=seed, duration_s=seconds, drift_ppm=50.0, jitter_ms=2.0))
    return capture, record


class _NoLinks:
    """Stands in for a SolveResult without a solve (--max-iterations 0): W has no links, so the clocks come from
    the track search alone."""

    def __init__(self, F: int, P: int):
        self.W = self
        self._F = F
        self.reconstructable = np.ones(P, dtype=bool)

    def to_csc(self) -> sp.csc_matrix:
        return sp.csc_matrix((self._F, self._F))


def score(
    scene: str,
    seed: int,
    capture: Any,
    record: Any,
    options: ClockOptions,
    solver: SolverOptions,
    cache: Path | None = None,
) -> dict[str, Any]:
    problem = build_problem(capture.cameras, capture.tracks, point_names=capture.truth.point_names)
    cached = cache / f"{scene}-{seed}-{solver.max_iterations}.pickle" if cache else None
    t0 = time.perf_counter()
    result: Any  # a SolveResult, or its stand-in without links
    if not solver.max_iterations:
        result = _NoLinks(problem.num_frames, problem.num_points)
    elif cached is not None and cached.exists():
        result = pickle.loads(cached.read_bytes())  # our own file from an earlier run of this script
    else:
        result = solve(problem, solver)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            cached.write_bytes(pickle.dumps(result))
    solve_s = time.perf_counter() - t0
    t0 = time.process_time()  # CPU time: the shared benchmark machine's wall time varies with its load
    clocks = estimate_clocks(problem, result, options)
    clocks_s = time.process_time() - t0
    links_only = estimate_clocks(problem, result, replace(options, search=SearchMode.NEVER))
    truth_index = capture.truth.index()
    true_time = np.array(
        [
            capture.truth.extra["time"][truth_index[(v, int(f))], 0]
            for v, f in zip(problem.frame_videos, problem.frames, strict=True)
        ]
    )
    true_clocks = {c.name: c for c in record.clocks}
    ref = true_clocks[clocks.reference]
    estimate = ref.global_time(clocks.global_time)
    std = ref.rate * clocks.global_std
    error = np.abs(estimate - true_time)
    known = np.isfinite(error)
    links_error = np.abs(ref.global_time(links_only.global_time) - true_time)
    fastest = 1.0 / max(c.fps for c in record.clocks)
    median = float(np.median(error[known])) if known.any() else float("nan")
    return {
        "scene": scene,
        "seed": seed,
        "videos": len(problem.video_names),
        "fps": [round(true_clocks[n].fps, 2) for n in problem.video_names],
        "frames": problem.num_frames,
        "points": problem.num_points,
        "median_ms": 1000 * median,
        "fraction_of_period": median / fastest,
        "p90_ms": 1000 * float(np.percentile(error[known], 90)) if known.any() else float("nan"),
        "within_2std": float(np.mean(error[known] <= 2 * std[known])) if known.any() else float("nan"),
        "unclocked_frames": int((~known).sum()),
        "methods": [v.method for v in clocks.videos],
        "offset_error_ms": [
            1000 * (ref.offset_s + ref.rate * v.offset - true_clocks[v.name].offset_s) for v in clocks.videos
        ],
        "link_scale_ms": 1000 * clocks.diagnostics.get("link_scale_s", float("nan")),
        # Only when W's links clock every video (else the reference's frames alone would be scored).
        "links_only_median_ms": 1000 * float(np.median(links_error))
        if np.isfinite(links_error).all()
        else float("nan"),
        "clocks_s": clocks_s,
        "solve_s": solve_s,
        "warnings": clocks.warnings,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="phones,flight")
    parser.add_argument("--seeds", default=None, help="comma-separated (default: phones 0,1,2; flight 0,1)")
    parser.add_argument("--seconds", type=float, default=None, help="scene length (default phones 4, flight 12)")
    parser.add_argument("--search", choices=[m.value for m in SearchMode], default=ClockOptions().search.value)
    parser.add_argument("--model", choices=[m.value for m in ClockModel], default="affine")
    parser.add_argument(
        "--max-iterations",
        type=int,
        default=40,
        help="solver alternations per stage (default 40: W's links settle long before the points); "
        "0: no solve, clocks from the tracks alone",
    )
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="keep each solve here and reuse it (to iterate on the clock options only)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("reconstruct.clocks.search").setLevel(logging.INFO)
    options = ClockOptions(search=SearchMode(args.search), model=ClockModel(args.model))
    rows: list[dict[str, Any]] = []
    print(
        f"solver {solver_version()}; search {args.search}, model {args.model}, "
        f"{args.max_iterations} solver iterations per stage"
    )
    header = (
        "| scene | seed | videos | fps | F | median ms | / fastest period | p90 ms | within 2 std | methods | "
        "links only: median ms | clocks CPU s | solve s |"
    )
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for scene in args.scenes.split(","):
        seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else ([0, 1, 2] if scene == "phones" else [0, 1])
        for seed in seeds:
            if scene == "phones":
                capture, record = phone_capture(seed, args.seconds or 4.0)
            elif scene == "flight":
                capture, record = flight_capture(seed, args.seconds or 12.0)
            else:
                parser.error(f"unknown scene {scene!r}")
            row = score(
                scene, seed, capture, record, options, SolverOptions(max_iterations=args.max_iterations), args.cache
            )
            rows.append(row)
            print(
                f"| {scene} | {seed} | {row['videos']} | {'/'.join(f'{f:g}' for f in row['fps'])} | "
                f"{row['frames']} | {row['median_ms']:.2f} | {row['fraction_of_period']:.3f} | "
                f"{row['p90_ms']:.2f} | {row['within_2std']:.2f} | {','.join(row['methods'])} | "
                f"{row['links_only_median_ms']:.2f} | {row['clocks_s']:.1f} | {row['solve_s']:.0f} |",
                flush=True,
            )
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
