"""The seed paper's tables with the temporal refinement (reconstruct/trajectory.py) side by side with its baselines.

    python benchmarks/refine_tables.py [--windows hdm05,cmu-jumps,squat,dropjump,walk] [--rows 30Hz,7.5Hz,noise1]
                                       [--distance 2700] [--cache DIR] [--json OUT] [--per-window]
    python benchmarks/refine_tables.py --rows all      # every row of the paper's three tables
    python benchmarks/refine_tables.py --from-json OUT [OUT2 ...]      # tables of earlier runs

Per (window, row) of benchmarks/paper_tables.py (same simulation, same seeds), four reconstructions are scored:

- init only: the nearly-intersecting ray bundles the seed solver starts from;
- seed: the self-expressive solver (reconstruct/solver/alternation.py, default options);
- refined, true times (oracle): reconstruct.trajectory from the seed result with the simulation's true capture times,
  i.e. trajectory triangulation given the true time order and spacing (the baseline the paper compares with,
  in the spirit of Valmadre & Lucey 2012);
- refined, estimated times: the same with times that the pipeline could know (`estimated_times`: every video's
  decoder times shifted by an unknown offset, clocks recovered by `clocks.estimate.estimate_clocks` with its
  default, affine, model);
- refined, estimated times + clock refinement: `clock_polish.refine_with_clocks` from those times (offsets and rates
  polished), the default of `dynrecon solve` when this script was written;
- dynrecon solve (default): what `dynrecon solve` does now, `temporal.recover_and_refine` with default
  TemporalOptions on the same shifted decoder times (offset-only clocks when every frame has a decoder time, an
  offset-only polish, guards that fall back to a plain refine); its clock time error and path (its `report`) are
  kept in the --json output and shown by --per-window.

The seed solves are the slow part; they are cached as .npz under `--cache` (keyed by window, row, length, camera
distance and `common.solver_sources_digest()`), so that refinement options can be swept without solving again.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy: one BLAS thread per process

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (
    PAPER,
    WINDOWS,
    load_window,
    percent_row,
    simulate,
    solver_sources_digest,
    solver_version,
    threshold_header,
)
from paper_tables import ROWS, Row

from reconstruct.clock_polish import refine_with_clocks
from reconstruct.clocks.estimate import estimate_clocks
from reconstruct.outputs.export import sequencing_order
from reconstruct.outputs.points import FramePoints
from reconstruct.solver.alternation import solve
from reconstruct.solver.initialize import fill_missing_points
from reconstruct.solver.problem import Problem
from reconstruct.stage import frame_points, sequencing
from reconstruct.temporal import TemporalOptions, recover_and_refine
from reconstruct.trajectory import RefineOptions, RobustLoss, SmoothnessRule, refine
from simulation.evaluate import evaluate
from simulation.simulate import SimulatedCapture

log = logging.getLogger("refine_tables")

DEFAULT_WINDOWS = "hdm05,cmu-jumps,squat,dropjump,walk"
# Windows never used for the reported tables: the refinement's defaults were tuned on these.
TUNING_WINDOWS = "run-5ms,freeform,run-4ms,cmu-late,sit-stand"
METHODS = ("init", "seed", "refined_true", "refined_estimated", "refined_clocks", "solve_default")
LABELS = {
    "init": "init only",
    "seed": "seed solver",
    "refined_true": "refined, true times (oracle)",
    "refined_estimated": "refined, estimated times",
    "refined_clocks": "refined, estimated times + clock refinement",
    "solve_default": "dynrecon solve (default)",
}


def simulate_row(
    window_index: int, row: Row, length: int, distance_mm: float | None
) -> tuple[SimulatedCapture, Problem]:
    """The capture of paper_tables.run_task (same options, same seed)."""
    window = WINDOWS[window_index]
    mocap = load_window(replace(window, seconds=min(window.seconds, length / 120.0)))
    options = row.simulation_options(mocap, window_index, distance_mm)
    capture, problem, _ = simulate(mocap, options)
    return capture, problem


def cache_path(cache: Path, window_index: int, row: Row, length: int, distance_mm: float | None, digest: str) -> Path:
    where = "pushback" if distance_mm is None else f"{distance_mm:g}mm"
    return cache / f"{WINDOWS[window_index].name}_{row.key}_{length}_{where}_{digest}.npz"


def seed_solve(problem: Problem, path: Path) -> dict[str, np.ndarray]:
    """Seed solver outputs (points, init, spectral order, W, seconds), from the cache or solved and cached."""
    if path.is_file():
        with np.load(path) as data:
            cached = {key: data[key] for key in data.files}
        if "w_data" in cached:
            return cached
    started = time.perf_counter()
    result = solve(problem)
    seconds = time.perf_counter() - started
    points = frame_points(problem, result)
    order = sequencing_order(points, sequencing(problem, result))
    init = fill_missing_points(result.init_points, problem.video_index)
    W = result.W.to_csc()
    out = {
        "points": result.points,
        "init": init,
        "order": order,
        "seconds": np.array(seconds),
        "w_data": W.data,
        "w_indices": W.indices,
        "w_indptr": W.indptr,
        "reconstructable": result.reconstructable,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    scratch = path.with_suffix(".tmp.npz")
    np.savez(scratch, **out)
    scratch.replace(path)
    return out


def score(problem: Problem, capture: SimulatedCapture, xyz: np.ndarray) -> list[float]:
    estimate = FramePoints(
        videos=problem.frame_videos,
        frames=problem.frames,
        point_names=problem.point_names,
        xyz=xyz,
        observed=problem.observed,
    )
    return [float(s) for s in evaluate(estimate, capture.truth).share_under]


class _CachedW:
    """The cached W behind SparseW's `to_csc`, the one call the clock recovery makes."""

    def __init__(self, W: Any) -> None:
        self._W = W

    def to_csc(self) -> Any:
        return self._W


class CachedResult:
    """The fields of reconstruct.solver.alternation.SolveResult that the clock recovery and the refinement read."""

    def __init__(self, problem: Problem, cached: dict[str, np.ndarray]) -> None:
        import scipy.sparse as sp

        F = problem.num_frames
        self.W = _CachedW(sp.csc_matrix((cached["w_data"], cached["w_indices"], cached["w_indptr"]), shape=(F, F)))
        self.reconstructable = cached["reconstructable"]
        self.points = cached["points"]


def shifted_problem(problem: Problem, seed: int) -> Problem:
    """The problem with every video's decoder times shifted by an unknown offset (uniform in +-1 s, as
    unsynchronized phones start at different moments): the clocks must really be recovered."""
    rng = np.random.default_rng(1000 + seed)
    offsets = rng.uniform(-1.0, 1.0, len(problem.video_names))
    return replace(problem, times=problem.times + offsets[problem.video_index])


def solve_default(
    problem: Problem, cached: dict[str, np.ndarray], seed: int, true_times: np.ndarray
) -> tuple[np.ndarray, dict[str, Any]]:
    """(F, P, 3) points of `dynrecon solve`'s temporal stage (recover_and_refine, default TemporalOptions) on the
    shifted problem, and its diagnostics: clock time error, path taken (report), clock model, seconds."""
    started = time.perf_counter()
    temporal = recover_and_refine(
        shifted_problem(problem, seed),
        CachedResult(problem, cached),  # type: ignore[arg-type]
        TemporalOptions(),
    )
    seconds = time.perf_counter() - started
    error = temporal.times - true_times
    finite = np.isfinite(error)
    error_ms = (
        float(1000 * np.median(np.abs(error[finite] - np.median(error[finite])))) if finite.any() else float("nan")
    )
    report = dict(temporal.report)
    if report.get("cost"):  # the polish guard: rejected when max(cost) > 1.01 cost[0] (or a rate moved far)
        report["cost_max_over_first"] = max(report["cost"]) / report["cost"][0]
    return temporal.points, {
        "seconds": seconds,
        "clock_time_error_ms_median": error_ms,
        "untimed_frames": int(np.sum(~finite)),
        "clock_model": temporal.clocks.model.value,
        "path": solve_path(temporal.report),
        "report": report,
    }


def solve_path(report: dict[str, Any]) -> str:
    """Which branch of recover_and_refine ran, in a few words."""
    if report.get("skipped"):
        return "not refined (" + str(report["skipped"]) + ")"
    if not report.get("refined"):
        return "not refined"
    if report.get("clock_polish_rejected"):
        return "polish rejected: plain refine"
    return "polished clocks"


def estimated_times(problem: Problem, cached: dict[str, np.ndarray], seed: int) -> tuple[np.ndarray, str]:
    """(F,) global times the pipeline could know, and how they were obtained.

    Every video's decoder times are shifted by an unknown offset (uniform in +-1 s, as unsynchronized phones start
    at different moments) and `estimate_clocks` recovers the global time from W. When it leaves a frame without a
    time: the spectral order of W (outputs.export.sequencing_order) at even spacing, which is the true spacing of
    the simulation's captures when the order is right.
    """
    clocks = estimate_clocks(shifted_problem(problem, seed), CachedResult(problem, cached))  # type: ignore[arg-type]
    times = np.asarray(clocks.global_time, dtype=float)
    if np.isfinite(times).all():
        return times, "clocks"
    log.warning(
        "estimate_clocks left %d frame(s) without a time: spectral order instead", int(np.sum(~np.isfinite(times)))
    )
    times = np.empty(problem.num_frames)
    times[cached["order"]] = np.arange(problem.num_frames) / (capture_rate(problem))
    return times, "spectral order"


def capture_rate(problem: Problem) -> float:
    """Captures per second of the simulation (its times are known to the benchmark, not to the method)."""
    span = float(np.nanmax(problem.times) - np.nanmin(problem.times))
    return (problem.num_frames - 1) / span if span > 0 else 1.0


def run_one(
    window_index: int,
    row: Row,
    length: int,
    distance_mm: float | None,
    cache: Path,
    options: RefineOptions,
    clock_refinement: bool,
    digest: str,
) -> dict[str, Any]:
    capture, problem = simulate_row(window_index, row, length, distance_mm)
    cached = seed_solve(problem, cache_path(cache, window_index, row, length, distance_mm, digest))
    true_times = capture.truth.extra["time"][:, 0]
    shares: dict[str, list[float]] = {
        "init": score(problem, capture, cached["init"]),
        "seed": score(problem, capture, cached["points"]),
    }
    started = time.perf_counter()
    oracle = refine(problem, cached["points"], true_times, options)
    refine_seconds = time.perf_counter() - started
    shares["refined_true"] = score(problem, capture, oracle.points)
    times, source = estimated_times(problem, cached, window_index)
    estimated = refine(problem, cached["points"], times, options)
    shares["refined_estimated"] = score(problem, capture, estimated.points)
    # Time error of the estimate after removing the gauge (a common offset).
    time_error = times - true_times
    time_error -= np.median(time_error)
    extra: dict[str, Any] = {}
    if clock_refinement:
        started = time.perf_counter()
        clocked = refine_with_clocks(problem, cached["points"], times, options)
        extra["clock_seconds"] = time.perf_counter() - started
        shares["refined_clocks"] = score(problem, capture, clocked.result.points)
        clock_error = clocked.times - true_times
        extra["clock_time_error_ms_median"] = float(1000 * np.median(np.abs(clock_error - np.median(clock_error))))
    default_points, extra["solve_default"] = solve_default(problem, cached, window_index, true_times)
    shares["solve_default"] = score(problem, capture, default_points)
    return {
        **extra,
        "window": WINDOWS[window_index].name,
        "row": row.key,
        "shares": shares,
        "times": source,
        "time_error_ms_median": float(1000 * np.median(np.abs(time_error))),
        "frames": problem.num_frames,
        "points": problem.num_points,
        "seed_seconds": float(cached["seconds"]),
        "refine_seconds": refine_seconds,
        "smoothness_median": float(np.nanmedian(oracle.smoothness)),
        "outliers": int(oracle.outliers.sum()),
    }


def print_tables(results: list[dict[str, Any]], per_window: bool) -> None:
    by_protocol: dict[str, list[dict[str, Any]]] = {}
    for item in results:
        by_protocol.setdefault(item["protocol"], []).append(item)
    for protocol, items in by_protocol.items():
        print(f"\n### {protocol}\n")
        print(threshold_header("setting / method", extra="windows"))
        keys = [r.key for r in ROWS if any(i["row"] == r.key for i in items)]
        for key in keys:
            done = [i for i in items if i["row"] == key]
            sources = sorted({i["times"] for i in done})
            for method in METHODS:
                have = [i["shares"][method] for i in done if method in i["shares"]]
                if not have:
                    continue
                mean = np.mean(have, axis=0)
                label = LABELS[method] + (f" ({', '.join(sources)})" if method == "refined_estimated" else "")
                print(percent_row(f"{key}: {label}", mean, f" {len(have)} |"))
            print(percent_row(f"{key}: paper", PAPER[key], " |"))
            if per_window:
                for i in done:
                    cells = ", ".join(f"{LABELS[m]} {100 * i['shares'][m][0]:.2f}" for m in METHODS if m in i["shares"])
                    clocked = f" -> {i['clock_time_error_ms_median']:.2f} ms" if "clock_seconds" in i else ""
                    if "solve_default" in i:
                        d = i["solve_default"]
                        clocked += (
                            f", default ({d['clock_model']} clocks, {d['path']}) "
                            f"{d['clock_time_error_ms_median']:.2f} ms"
                        )
                    print(
                        f"| &nbsp;&nbsp;{i['window']} (<10 mm) | {cells}; F={i['frames']}, time error "
                        f"{i['time_error_ms_median']:.2f} ms{clocked}, smoothness {i['smoothness_median']:.2g}, "
                        f"{i['outliers']} outliers, refine {i['refine_seconds']:.1f} s |"
                    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--windows", default=DEFAULT_WINDOWS, help="comma-separated window names (common.WINDOWS)")
    parser.add_argument(
        "--rows", default="30Hz,7.5Hz,noise1,noise3", help="comma-separated row keys of paper_tables.py, or 'all'"
    )
    parser.add_argument(
        "--distance",
        default="2700",
        help="camera distance in mm (the paper's 2700), or 'push' for cameras pushed back until "
        "every point is inside the images; comma-separated for both",
    )
    parser.add_argument("--length", type=int, default=300)
    parser.add_argument(
        "--cache", type=Path, default=Path("/tmp/dynrecon_refine_cache"), help="folder of cached seed solves"
    )
    parser.add_argument("--loss", default=RobustLoss.HUBER.value, choices=[x.value for x in RobustLoss])
    parser.add_argument("--rule", default=SmoothnessRule.GCV.value, choices=[x.value for x in SmoothnessRule])
    parser.add_argument("--smoothness", type=float, default=1.0, help="lambda for --rule fixed")
    parser.add_argument(
        "--no-clock-refinement", action="store_true", help="skip refine_with_clocks (the slowest column)"
    )
    parser.add_argument("--json", type=Path, help="write every result (after each window) to this file")
    parser.add_argument("--from-json", type=Path, nargs="+", help="print the tables of earlier --json files")
    parser.add_argument("--per-window", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    for noisy in ("reconstruct", "common"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    if args.from_json:
        earlier = [item for path in args.from_json for item in json.loads(path.read_text())["results"]]
        print_tables(earlier, args.per_window)
        return 0
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    names = [w.name for w in WINDOWS]
    rows = {r.key: r for r in ROWS}
    if args.rows == "all":
        args.rows = ",".join(rows)
    unknown = [w for w in args.windows.split(",") if w not in names] + [
        r for r in args.rows.split(",") if r not in rows
    ]
    if unknown:
        raise SystemExit(f"unknown window or row: {', '.join(unknown)}")
    options = RefineOptions(loss=RobustLoss(args.loss), rule=SmoothnessRule(args.rule), smoothness=args.smoothness)
    version = solver_version()
    digest = solver_sources_digest()  # at the start: an edit during the run must not mix two solvers
    print(f"solver: {version} (sources digest {digest}); refine options: {options}", flush=True)
    results: list[dict[str, Any]] = []
    for distance_text in args.distance.split(","):
        distance = None if distance_text == "push" else float(distance_text)
        protocol = (
            "cameras pushed back (default protocol)"
            if distance is None
            else f"paper protocol, cameras at {distance / 1000:g} m"
        )
        for key in args.rows.split(","):
            for name in args.windows.split(","):
                try:
                    item = run_one(
                        names.index(name),
                        rows[key],
                        args.length,
                        distance,
                        args.cache,
                        options,
                        not args.no_clock_refinement,
                        digest,
                    )
                except Exception:  # keep the other windows' results
                    log.exception("%s / %s failed", name, key)
                    continue
                item["protocol"] = protocol
                results.append(item)
                s = item["shares"]
                log.info(
                    "%s / %s / %s: <10 mm init %.2f seed %.2f refined(true) %.2f refined(%s) %.2f, "
                    "+clocks %.2f, default %.2f (%s, %.2f ms)",
                    protocol,
                    name,
                    key,
                    100 * s["init"][0],
                    100 * s["seed"][0],
                    100 * s["refined_true"][0],
                    item["times"],
                    100 * s["refined_estimated"][0],
                    100 * s.get("refined_clocks", [np.nan])[0],
                    100 * s["solve_default"][0],
                    item["solve_default"]["path"],
                    item["solve_default"]["clock_time_error_ms_median"],
                )
                if args.json:
                    args.json.write_text(
                        json.dumps({"solver": version, "options": str(options), "results": results}, indent=1) + "\n"
                    )
    print_tables(results, args.per_window)
    return 0


if __name__ == "__main__":
    sys.exit(main())
