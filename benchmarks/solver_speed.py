"""Speed and peak memory of the solver, and its W-step against a general-purpose QP solver.

    python benchmarks/solver_speed.py [--sizes 250,700,2000] [--repeats 3] [--threads-frames 700]
                                      [--qp-sizes 100,250] [--qp osqp,clarabel] [--json OUT]

Data: CMU 01_01 (playground jumps, 120 Hz, ../shared/data/mocap) from its first frame, F consecutive captures =
30 Hz per camera with the paper's 4 virtual cameras, noise-free. The file has 41 complete markers; 3 virtual markers
(midpoints of marker pairs, rigidly attached like a joint centre) make P = 44, the paper's HDM05 count.

1. Full solve (`reconstruct.solver.solve`, default options) for each F, each size in a fresh subprocess with one
   BLAS thread: median wall time of `--repeats` solves (sizes above 700 frames: one solve), the stage split, and the
   peak resident memory of that process (getrusage ru_maxrss: counts numpy/scipy native allocations, which
   tracemalloc does not) next to its resident memory just before the first solve.
2. BLAS threads: the full solve at `--threads-frames` frames with 1 and 2 threads (threadpoolctl), fresh processes.
3. W-step: `solver.wstep.solve_w` (cold start) against cvxpy with OSQP / Clarabel on the same problem: shapes =
   the true positions in the solver's normalized units, W a dense F x F variable with W_jf = 0 where video(j) =
   video(f) (the diagonal included), columns on the simplex, lambda1 = 0.05. The general solver's answer is
   projected onto the feasible set before its objective is compared (first-order solvers stop slightly infeasible).

Needs `pip install cvxpy osqp` (the project's `bench` extra) for part 3; parts 1-2 run without it.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import require_mocap_dir, simulate, solver_version

from reconstruct.outputs.mocap import Mocap, read_mocap
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import camera_normalization
from reconstruct.solver.wstep import WStepOptions, objective_full, solve_w
from simulation.simulate import SimulatedCapture, SimulationOptions

log = logging.getLogger("solver_speed")

CMU_FILE = "cmu/cmu_01_01.c3d"
POINTS = 44
LAMBDA1 = 0.05
RESULT_PREFIX = "RESULT "


def capture_of(frames: int, seed: int = 0) -> tuple[SimulatedCapture, Problem]:
    """`frames` captures of CMU 01_01 with P = 44 points, 4 cameras at 30 Hz each."""
    mocap = read_mocap(require_mocap_dir() / CMU_FILE)
    missing = mocap.missing()
    markers = np.flatnonzero(missing.mean(axis=0) <= 0.1)
    complete = np.flatnonzero(~missing[:, markers].any(axis=1))
    if len(complete) < frames:
        raise SystemExit(f"{CMU_FILE} has only {len(complete)} complete frames; ask for at most that many")
    rows = complete[:frames]
    xyz = mocap.xyz[rows][:, markers]
    names = [mocap.marker_names[m] for m in markers]
    extra = POINTS - len(names)
    if extra > 0:  # virtual markers: midpoints of the pairs (0, 1), (2, 3), ...
        pairs = [(2 * i, 2 * i + 1) for i in range(extra)]
        xyz = np.concatenate([xyz, np.stack([(xyz[:, a] + xyz[:, b]) / 2 for a, b in pairs], axis=1)], axis=1)
        names += [f"mid_{names[a]}_{names[b]}" for a, b in pairs]
    xyz, names = xyz[:, :POINTS], names[:POINTS]
    window = Mocap(
        xyz=np.ascontiguousarray(xyz),
        rate=mocap.rate,
        marker_names=names,
        times=mocap.times[rows] - mocap.times[rows[0]],
        path=mocap.path,
    )
    capture, problem, _ = simulate(window, SimulationOptions(seed=seed))
    return capture, problem


# ------------------------------------------------------------------------------------------------------------
# Part 1-2: full solve in a fresh process


def child_full(frames: int, threads: int, repeats: int) -> dict[str, Any]:
    from common import solve_and_score
    from threadpoolctl import threadpool_info, threadpool_limits

    threadpool_limits(threads)
    capture, problem = capture_of(frames)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    runs = [solve_and_score(capture, problem)[0] for _ in range(repeats)]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    times = [r.seconds for r in runs]
    median_run = sorted(runs, key=lambda r: r.seconds)[len(runs) // 2]
    return {
        "frames": problem.num_frames,
        "points": problem.num_points,
        "threads": threads,
        "times_s": times,
        "median_s": statistics.median(times),
        "timings": median_run.timings,
        "iterations": median_run.iterations,
        "peak_rss_mb": peak,
        "rss_before_solve_mb": rss_before,
        "share_under_10mm": median_run.shares[0],
        "blas": [
            {k: v for k, v in info.items() if k in ("internal_api", "num_threads", "version")}
            for info in threadpool_info()
        ],
    }


def run_child(frames: int, threads: int, repeats: int) -> dict[str, Any]:
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[name] = str(threads)
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child-frames",
        str(frames),
        "--child-threads",
        str(threads),
        "--repeats",
        str(repeats),
    ]
    log.info("full solve F=%d, %d thread(s), %d repeat(s) ...", frames, threads, repeats)
    started = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    lines = [line for line in done.stdout.splitlines() if line.startswith(RESULT_PREFIX)]
    if done.returncode != 0 or not lines:
        raise SystemExit(f"child F={frames} threads={threads} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(lines[-1][len(RESULT_PREFIX) :])
    log.info("... %.0f s wall", time.perf_counter() - started)
    return result


def print_full(results: list[dict[str, Any]]) -> None:
    print("\n### Full solve (1 BLAS thread, fresh process per size)\n")
    print(
        "| F | P | median s (repeats) | initialize | W-step | X-step | iterations (stages) | peak RSS MB | "
        "RSS before solve MB | <10 mm |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        t = r["timings"]
        print(
            f"| {r['frames']} | {r['points']} | {r['median_s']:.1f} ({len(r['times_s'])}) | "
            f"{t.get('initialize', 0):.2f} | {t.get('w_step', 0):.1f} | {t.get('x_step', 0):.1f} | "
            f"{'+'.join(str(i) for i in r['iterations'])} | {r['peak_rss_mb']:.0f} | "
            f"{r['rss_before_solve_mb']:.0f} | {100 * r['share_under_10mm']:.2f} % |"
        )


def print_threads(results: list[dict[str, Any]]) -> None:
    print("\n### BLAS threads (threadpoolctl), full solve\n")
    print("| F | threads | median s (repeats) | W-step s | X-step s | BLAS |")
    print("|---|---|---|---|---|---|")
    for r in results:
        blas = ", ".join(f"{b.get('internal_api')} {b.get('version')}" for b in r["blas"])
        print(
            f"| {r['frames']} | {r['threads']} | {r['median_s']:.1f} ({len(r['times_s'])}) | "
            f"{r['timings'].get('w_step', 0):.1f} | {r['timings'].get('x_step', 0):.1f} | {blas} |"
        )
    if len(results) >= 2:
        best = min(results, key=lambda r: r["median_s"])
        worst = max(results, key=lambda r: r["median_s"])
        print(f"\nfaster: {best['threads']} thread(s), {worst['median_s'] / best['median_s']:.2f}x")


# ------------------------------------------------------------------------------------------------------------
# Part 3: W-step against a general QP solver


def wstep_problem(frames: int) -> tuple[np.ndarray, np.ndarray, int]:
    """shapes (F, 3P) in normalized units (true positions), video_index (F,), P."""
    capture, problem = capture_of(frames)
    rows = capture.truth.index()
    order = np.array([rows[(v, int(f))] for v, f in zip(problem.frame_videos, problem.frames, strict=True)])
    normalization = camera_normalization(problem.centers, problem.video_index)
    points = normalization.apply(capture.truth.xyz[order])  # (F, P, 3)
    return points.reshape(len(order), -1), problem.video_index, problem.num_points


def frank_wolfe_gap(shapes: np.ndarray, video_index: np.ndarray, W: np.ndarray, P: int) -> float:
    """Certificate of a feasible W (F, F): sum over columns of <grad_f, w_f> - min over allowed j of grad_jf.

    It bounds g(W) - min g from above (convexity), so it needs no reference solution. Dense: small F only.
    """
    F = len(shapes)
    G = shapes @ shapes.T
    grad = 2.0 / (F * P) * (G @ W - G) + 4.0 * LAMBDA1 / F * (W - W.T)
    allowed = video_index[:, None] != video_index[None, :]
    lowest = np.where(allowed, grad, np.inf).min(axis=0)
    return float(np.sum(np.einsum("jf,jf->f", grad, W) - lowest))


# A tighter setting of our W-step, to show how close to the optimum the working set gets when asked, and the exact one
# (WStepOptions.exact).
TIGHT: dict[str, Any] = {"kkt_tolerance": 1e-6, "max_rounds": 20}


def ours(
    shapes: np.ndarray, video_index: np.ndarray, P: int, repeats: int, options: WStepOptions, settings: dict[str, Any]
) -> dict[str, Any]:
    """Our W-step with `options`, reported under `settings` (how they differ from the default)."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        W, stats = solve_w(shapes, video_index, P, options)
        times.append(time.perf_counter() - started)
    W_csc = W.to_csc()
    return {
        "settings": settings,
        "seconds": statistics.median(times),
        "times_s": times,
        "objective": objective_full(shapes, W_csc, LAMBDA1, P),
        "nonzeros": int(W_csc.nnz),
        "fw_gap": frank_wolfe_gap(shapes, video_index, W_csc.toarray(), P),
        "working_set": stats.working_set,
        "rounds": stats.rounds,
    }


def general_qp(shapes: np.ndarray, video_index: np.ndarray, P: int, solver: str) -> dict[str, Any]:
    """The W-step as a user would write it in cvxpy: dense W, masks as equality constraints.

    The objective is multiplied by F P (same minimizer): at 1/(FP) scale it is ~1e-7 and the solvers' absolute
    tolerances stopped OSQP and Clarabel 5-10 % above the optimum (measured at F = 60).
    """
    import cvxpy as cp
    import scipy.sparse as sp

    from reconstruct.solver.simplex import project_rows_to_simplex

    F = len(shapes)
    X = shapes.T  # (3P, F): column f = shape of frame f
    forbidden = (video_index[:, None] == video_index[None, :]).astype(float)  # W_jf = 0: same video, diagonal
    W = cp.Variable((F, F))
    objective = cp.sum_squares(X - X @ W) + LAMBDA1 * P * cp.sum_squares(W - W.T)
    constraints = [W >= 0, cp.sum(W, axis=0) == 1, cp.multiply(forbidden, W) == 0]
    qp = cp.Problem(cp.Minimize(objective), constraints)
    started = time.perf_counter()
    try:
        qp.solve(solver=solver.upper())
    except (cp.error.SolverError, ValueError) as error:
        return {"solver": solver, "error": str(error)}
    seconds = time.perf_counter() - started
    if W.value is None:
        return {"solver": solver, "error": f"status {qp.status}"}
    raw = np.asarray(W.value)
    allowed = forbidden == 0
    feasible = project_rows_to_simplex(raw.T, allowed.T).T  # columns onto the masked simplex
    stats = qp.solver_stats
    return {
        "solver": solver,
        "status": qp.status,
        "seconds": seconds,
        "solver_seconds": float(stats.solve_time) if stats.solve_time is not None else float("nan"),
        "objective_raw": float(qp.value) / (F * P),
        "objective": objective_full(shapes, sp.csc_matrix(feasible), LAMBDA1, P),
        "fw_gap": frank_wolfe_gap(shapes, video_index, feasible, P),
        "infeasibility": float(
            max(np.abs(raw.sum(axis=0) - 1).max(), max(0.0, -raw.min()), np.abs(raw[~allowed]).max())
        ),
        "nonzeros_above_1e-6": int((feasible > 1e-6).sum()),
    }


def print_qp(rows: list[dict[str, Any]]) -> None:
    print("\n### W-step: ours (working set + exact active set, cold start) vs cvxpy (dense W)\n")
    print(
        "objective g(W) in the solver's units; 'above best' = (g - lowest g found by any solver) / lowest g; "
        "cvxpy answers projected onto the feasible set before scoring.\n"
    )
    print(
        "| F | P | solver | seconds (solver only) | ours faster by | objective g | above best | "
        "FW gap / g | infeasibility before projection | nnz |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        o = row["ours"]
        found = [o["objective"]] + [t["objective"] for t in row["general"] if "error" not in t]
        variants = [row[key] for key in ("ours_tight", "ours_exact") if key in row]
        found += [t["objective"] for t in variants]
        best = min(found)

        def above(value: float, best: float = best) -> str:
            return f"{100 * (value - best) / best:.2f} %"

        print(
            f"| {row['frames']} | {row['points']} | ours (default) | {o['seconds']:.3f} (median of "
            f"{len(o['times_s'])}) | 1 | {o['objective']:.9e} | {above(o['objective'])} | "
            f"{o['fw_gap'] / o['objective']:.1e} | 0 | {o['nonzeros']} |"
        )
        for t in variants:
            print(
                f"| {row['frames']} | {row['points']} | ours {t['settings']} | {t['seconds']:.3f} | "
                f"({t['seconds'] / o['seconds']:.1f}x slower) | {t['objective']:.9e} | {above(t['objective'])} | "
                f"{t['fw_gap'] / t['objective']:.1e} | 0 | "
                f"{t['nonzeros']} |"
            )
        for t in row["general"]:
            if "error" in t:
                print(f"| {row['frames']} | {row['points']} | {t['solver']} | failed: {t['error']} | | | | | | |")
                continue
            print(
                f"| {row['frames']} | {row['points']} | cvxpy {t['solver']} ({t['status']}) | {t['seconds']:.2f} "
                f"({t['solver_seconds']:.2f}) | {t['seconds'] / o['seconds']:.0f}x "
                f"({t['solver_seconds'] / o['seconds']:.0f}x) | {t['objective']:.9e} | {above(t['objective'])} | "
                f"{t['fw_gap'] / t['objective']:.1e} | {t['infeasibility']:.1e} | {t['nonzeros_above_1e-6']} |"
            )
    for row in rows:  # the exact mode against the general solvers: the same problem solved to its optimum
        if "ours_exact" not in row:
            continue
        exact = row["ours_exact"]
        for t in row["general"]:
            if "error" not in t:
                print(
                    f"\nF = {row['frames']}: ours exact {exact['seconds']:.2f} s, cvxpy {t['solver']} "
                    f"{t['seconds']:.2f} s: {t['seconds'] / exact['seconds']:.0f}x faster"
                )


# ------------------------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="250,700,2000", help="frame counts of the full solve ('' = skip)")
    parser.add_argument("--repeats", type=int, default=3, help="solves per size up to 700 frames (median)")
    parser.add_argument("--threads-frames", type=int, default=700, help="F of the 1 vs 2 thread run (0 = skip)")
    parser.add_argument("--qp-sizes", default="100,250", help="frame counts of the W-step comparison ('' = skip)")
    parser.add_argument("--qp", default="osqp,clarabel", help="cvxpy solvers to compare with")
    parser.add_argument("--json", type=Path, help="write all numbers to this file")
    parser.add_argument("--child-frames", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-threads", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("reconstruct").setLevel(logging.WARNING)
    if args.child_frames is not None:
        result = child_full(args.child_frames, args.child_threads, args.repeats)
        print(RESULT_PREFIX + json.dumps(result), flush=True)
        return 0

    require_mocap_dir()
    print(f"cores: {os.cpu_count()}, load average at start: {os.getloadavg()[0]:.1f}; data: {CMU_FILE}, P = {POINTS}")
    report: dict[str, Any] = {"solver": solver_version()}
    print(f"solver: {report['solver']}")
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    full = [run_child(F, 1, args.repeats if F <= 700 else 1) for F in sizes]
    report["full"] = full
    if full:
        print_full(full)

    if args.threads_frames:
        F = args.threads_frames
        repeats = args.repeats if F <= 700 else 1
        one = next((r for r in full if r["frames"] == F), None) or run_child(F, 1, repeats)
        threads = [one, run_child(F, 2, repeats)]
        report["threads"] = threads
        print_threads(threads)

    qp_rows = []
    for F in [int(s) for s in args.qp_sizes.split(",") if s.strip()]:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1):
            shapes, video_index, P = wstep_problem(F)
            log.info("W-step F=%d: ours ...", F)
            default = WStepOptions(lambda1=LAMBDA1)
            row: dict[str, Any] = {
                "frames": F,
                "points": P,
                "ours": ours(shapes, video_index, P, args.repeats, default, {}),
                "ours_tight": ours(shapes, video_index, P, 1, WStepOptions(lambda1=LAMBDA1, **TIGHT), TIGHT),
                "ours_exact": ours(shapes, video_index, P, 1, WStepOptions.exact(lambda1=LAMBDA1), {"exact": True}),
            }
            log.info(
                "... ours %s; tight %s; exact %s",
                json.dumps(row["ours"]),
                json.dumps(row["ours_tight"]),
                json.dumps(row["ours_exact"]),
            )
            row["general"] = []
            for solver in [s.strip() for s in args.qp.split(",") if s.strip()]:
                log.info("W-step F=%d: cvxpy %s ...", F, solver)
                row["general"].append(general_qp(shapes, video_index, P, solver))
                log.info("... %s", json.dumps(row["general"][-1]))  # a long run keeps what it has measured
        qp_rows.append(row)
        if args.json:
            args.json.write_text(json.dumps({**report, "wstep": qp_rows}, indent=1) + "\n")
    report["wstep"] = qp_rows
    if qp_rows:
        print_qp(qp_rows)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f} (2 shared cores: other work inflates times)")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
