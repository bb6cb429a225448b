"""CPU time and peak memory of the windowed (long-capture) initialization
(`reconstruct.solver.candidates.coarse_to_fine_init`), against the same file at another git revision, with a check that
both give the same anchors, partners, costs and depths.

    python benchmarks/window_init_speed.py [--sizes cmu:700,cmu:2000,long:5000,long:20000] [--repeats 5]
                                           [--reference REV]

Data: `cmu:F` is the solver benchmark's capture (`solver_speed.capture_of`: CMU 01_01, P = 44, 4 cameras at 30 Hz);
`long:F` the long-capture benchmark's (`long_capture.long_motion`: complexknee played forward and backward, P = 20,
4 cameras at 30 Hz, 2.7 m). Rays and centers in the solver's normalized units, decoder times passed as the solver
does. One BLAS thread (threadpoolctl). Time: `time.process_time` of one call, median of `--repeats`, old and new
interleaved so that both see the same load on a shared machine. Peak memory: tracemalloc's peak during one call
(numpy's buffers are traced), beyond the inputs. `--reference REV` takes the search from REV and the anchor rules
(`consistent_anchors`, `window_pool`, ...: SHARED_RULES) from the current file, so that only the search is compared.

Differences: partners that differ are reported as ties when the explicit bundle distance (`pair_distances`) of both
choices lies below `--tie` times the median cost: noise-free captures hold frames of two videos at the same
instant, whose D is 0 up to rounding (~1e-32), and which of several such zeros is least is rounding noise. Costs are
compared relatively above that level, absolutely below it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import tracemalloc
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import module_at_revision  # (also puts the repository root on sys.path)

from reconstruct.solver import candidates
from reconstruct.solver.rays import camera_normalization, viewing_rays

SHARED_RULES = ("consistent_anchors", "_ransac_line", "anchor_tolerance", "window_pool", "_fill_anchor_gaps")


def load_revision(revision: str) -> ModuleType:
    """reconstruct/solver/candidates.py as of a git revision, as a module of its own."""
    module = module_at_revision("reconstruct/solver/candidates.py", revision, "candidates_reference")
    # The anchor rules are another job's, and change on their own: the current ones in both, so that the
    # comparison is of the search alone.
    for name in SHARED_RULES:
        setattr(module, name, getattr(candidates, name))
    return module


def inputs(size: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    kind, frames = size.split(":")
    if kind == "cmu":
        from solver_speed import capture_of

        _, problem = capture_of(int(frames))
    elif kind == "long":
        from long_capture import long_problem

        _, problem = long_problem(int(frames))
    else:
        raise SystemExit(f"--sizes: unknown capture kind {kind!r} (cmu or long)")
    rays = viewing_rays(problem)
    centers = camera_normalization(problem.centers, problem.video_index).apply(problem.centers)
    return centers, rays, problem.video_index, problem.times


def call(module: ModuleType, args: tuple[Any, ...]) -> tuple[float, Any]:
    centers, rays, video_index, times = args
    started = time.process_time()
    result = module.coarse_to_fine_init(centers, rays, video_index, module.CandidateOptions(), times=times)
    return time.process_time() - started, result


def peak_mb(module: ModuleType, args: tuple[Any, ...]) -> float:
    tracemalloc.start()
    call(module, args)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def differences(args: tuple[Any, ...], old: Any, new: Any, tie: float) -> dict[str, Any]:
    centers, rays = args[0], args[1]
    (init_old, anchor_old), (init_new, anchor_new) = old, new
    scale = float(np.median(init_old.cost[np.isfinite(init_old.cost)]))
    differ = np.flatnonzero(init_old.partner != init_new.partner)
    D_old, _ = candidates.pair_distances(centers, rays, differ, init_old.partner[differ])
    D_new, _ = candidates.pair_distances(centers, rays, differ, init_new.partner[differ])
    ties = int(np.sum((D_old <= tie * scale) & (D_new <= tie * scale)))
    same = (init_old.partner == init_new.partner) & np.isfinite(init_old.cost)
    large = same & (init_old.cost > tie * scale)
    small = same & ~large
    cost_rel = np.abs(init_new.cost[large] - init_old.cost[large]) / init_old.cost[large]
    depth_rel = np.abs(init_new.depth[same] - init_old.depth[same]) / np.abs(init_old.depth[same])
    return {
        "anchors_differ": int(np.sum(anchor_old != anchor_new)),
        "partners_differ": len(differ),
        "ties": ties,
        "cost_rel": float(cost_rel.max(initial=0.0)),
        "cost_abs_small": float(np.abs(init_new.cost[small] - init_old.cost[small]).max(initial=0.0)),
        "depth_rel": float(np.nanmax(depth_rel, initial=0.0)),
        "nan_depths_same": bool(np.array_equal(np.isnan(init_old.depth), np.isnan(init_new.depth))),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="cmu:700,cmu:2000,long:5000,long:20000")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--reference", default=None, help="git revision to compare with, e.g. HEAD~1")
    parser.add_argument("--tie", type=float, default=1e-12, help="D below this times the median cost counts as 0")
    args = parser.parse_args(argv)
    threadpool_limits(1)
    reference = load_revision(args.reference) if args.reference else None
    rows = []
    for size in args.sizes.split(","):
        data = inputs(size)
        modules = {"new": candidates} | ({"old": reference} if reference else {})
        times: dict[str, list[float]] = {name: [] for name in modules}
        results: dict[str, Any] = {}
        for _ in range(args.repeats):
            for name, module in modules.items():
                seconds, results[name] = call(module, data)
                times[name].append(seconds)
        peaks = {name: peak_mb(module, data) for name, module in modules.items()}
        row: dict[str, Any] = {"size": size, "F": len(data[2]), "P": data[1].shape[1]}
        for name in modules:
            row[f"{name}_s"] = statistics.median(times[name])
            row[f"{name}_mb"] = peaks[name]
        if reference:
            row |= differences(data, results["old"], results["new"], args.tie)
        rows.append(row)
        print(row, flush=True)
    print(f"\nCPU s: median of {args.repeats}, 1 BLAS thread; peak MB: tracemalloc, beyond the inputs")
    if reference:
        print(
            f"| capture | F | P | {args.reference} s | new s | speed-up | {args.reference} MB | new MB | "
            "partners differ (ties) | anchors differ | cost rel | depth rel |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(
                f"| {r['size'].split(':')[0]} | {r['F']} | {r['P']} | {r['old_s']:.3f} | {r['new_s']:.3f} | "
                f"{r['old_s'] / r['new_s']:.1f}x | {r['old_mb']:.0f} | {r['new_mb']:.0f} | "
                f"{r['partners_differ']} ({r['ties']}) | {r['anchors_differ']} | {r['cost_rel']:.1e} | "
                f"{r['depth_rel']:.1e} |"
            )
    else:
        print("| capture | F | P | CPU s | peak MB |\n|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['size'].split(':')[0]} | {r['F']} | {r['P']} | {r['new_s']:.3f} | {r['new_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
