"""CPU time and peak memory of the solver's pairwise initialization (`reconstruct.solver.initialize.initialize_depths`),
optionally against the same file at another git revision, with a check that both pick the same partners.

    python benchmarks/init_speed.py [--sizes 700,2000] [--repeats 5] [--missing 0,0.3] [--reference REV]

Data: the solver benchmark's capture (`solver_speed.capture_of`: CMU 01_01, P = 44, 4 cameras at 30 Hz), rays in
the solver's normalized units; `--missing` sets that share of the rays to NaN (fixed seed). One BLAS thread
(threadpoolctl). Time: `time.process_time` of one call, median of `--repeats`, old and new interleaved so that both
see the same load on a shared machine. Peak memory: tracemalloc's peak during one call (numpy's buffers are
traced), beyond the inputs. `--reference REV` loads `reconstruct/solver/initialize.py` as of REV (e.g. HEAD~3) by
`git show`, and compares partners (exact), costs and depths (largest relative difference) with the current code;
`--brute-force N` also checks the current costs of N frames against `closest_ray_points` pair by pair.
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

from common import module_at_revision
from solver_speed import capture_of

from reconstruct.solver import initialize
from reconstruct.solver.rays import camera_normalization, viewing_rays


def load_revision(revision: str) -> ModuleType:
    """reconstruct/solver/initialize.py as of a git revision, as a module of its own."""
    return module_at_revision("reconstruct/solver/initialize.py", revision, "initialize_reference")


def inputs(frames: int, missing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    _, problem = capture_of(frames)
    rays = viewing_rays(problem)
    centers = camera_normalization(problem.centers, problem.video_index).apply(problem.centers)
    if missing > 0:
        rays[np.random.default_rng(0).random(rays.shape[:2]) < missing] = np.nan
    return centers, rays, problem.video_index


def measure(module: ModuleType, args: tuple[np.ndarray, ...]) -> tuple[float, Any]:
    started = time.process_time()
    result = module.initialize_depths(*args)
    return time.process_time() - started, result


def peak_mb(module: ModuleType, args: tuple[np.ndarray, ...]) -> float:
    tracemalloc.start()
    module.initialize_depths(*args)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def brute_force_error(args: tuple[np.ndarray, ...], result: Any, count: int) -> float:
    """Largest relative difference of the chosen pairs' D from an explicit closest-point evaluation."""
    centers, rays, _ = args
    frames = np.flatnonzero(result.partner >= 0)[:count]
    partner = result.partner[frames]
    _, _, gap = initialize.closest_ray_points(
        centers[frames][:, None], rays[frames], centers[partner][:, None], rays[partner]
    )
    usable = np.isfinite(gap)
    D = np.where(usable, gap, 0.0).sum(axis=1) / usable.sum(axis=1)
    return float(np.max(np.abs(result.cost[frames] - D) / D)) if len(frames) else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="700,2000")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--missing", default="0,0.3", help="shares of rays set to NaN, comma-separated")
    parser.add_argument("--reference", default=None, help="git revision of reconstruct/solver/initialize.py to compare")
    parser.add_argument("--brute-force", type=int, default=200, help="frames checked pair by pair (0: none)")
    options = parser.parse_args()
    reference = load_revision(options.reference) if options.reference else None
    rows = []
    with threadpool_limits(1):
        for frames in (int(s) for s in options.sizes.split(",")):
            for missing in (float(s) for s in options.missing.split(",")):
                args = inputs(frames, missing)
                new_times, old_times = [], []
                for _ in range(options.repeats):
                    seconds, new = measure(initialize, args)
                    new_times.append(seconds)
                    if reference is not None:
                        seconds, old = measure(reference, args)
                        old_times.append(seconds)
                row: dict[str, Any] = {
                    "F": frames,
                    "missing": missing,
                    "new_s": statistics.median(new_times),
                    "new_mb": peak_mb(initialize, args),
                    "brute": brute_force_error(args, new, options.brute_force),
                }
                if reference is not None:
                    finite = np.isfinite(old.cost)
                    both = np.isfinite(old.depth)
                    row |= {
                        "old_s": statistics.median(old_times),
                        "old_mb": peak_mb(reference, args),
                        "same_partner": bool(np.array_equal(old.partner, new.partner)),
                        "cost_rel": float(np.max(np.abs(new.cost[finite] / old.cost[finite] - 1), initial=0)),
                        "depth_rel": float(np.max(np.abs(new.depth[both] / old.depth[both] - 1), initial=0)),
                        "same_nan": bool(np.array_equal(both, np.isfinite(new.depth))),
                    }
                rows.append(row)
    print(f"\n### Pairwise initialization, 1 BLAS thread, median of {options.repeats} (CPU s)\n")
    if reference is None:
        print("| F | missing | CPU s | peak MB | D vs brute force (rel) |\n|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['F']} | {r['missing']:.0%} | {r['new_s']:.3f} | {r['new_mb']:.1f} | {r['brute']:.1e} |")
        return
    print(
        f"| F | missing | {options.reference} CPU s | now CPU s | speed-up | {options.reference} peak MB | "
        "now peak MB | same partners | cost rel. diff | depth rel. diff | D vs brute force (rel) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['F']} | {r['missing']:.0%} | {r['old_s']:.3f} | {r['new_s']:.3f} | "
            f"{r['old_s'] / r['new_s']:.1f}x | {r['old_mb']:.1f} | {r['new_mb']:.1f} | "
            f"{'yes' if r['same_partner'] and r['same_nan'] else 'NO'} | {r['cost_rel']:.1e} | "
            f"{r['depth_rel']:.1e} | {r['brute']:.1e} |"
        )


if __name__ == "__main__":
    main()
