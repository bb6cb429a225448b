"""X-step alone (`solver.xstep.solve_x`): CPU time per call and CG iterations against F, the current code beside
a baseline revision, on the inputs the solver really gives it.

    python benchmarks/xstep_speed.py [--real 700,2000] [--synthetic 5000,20000] [--baseline 6eeb4a6]
                                     [--repeats 3] [--threads 1] [--json OUT]

Inputs
* real (`--real`): every X-step of a full solve (default options), recorded by wrapping `alternation.solve_x`:
  F = 700 is CMU 01_01 with P = 44 (`solver_speed.capture_of`), larger F are complexknee with P = 20
  (`long_capture.long_motion`, 4 cameras at 2.7 m, 30 Hz each). The calls are replayed in order, with the solve's own
  warm starts.
* synthetic (`--synthetic`, for F where a full solve is too slow): complexknee as above; W is one windowed W-step
  (`solver.wstep.solve_w`, candidates +-12 frames around the true time in each other video) on the true points
  plus a smooth error of 3 mm-ish (normalized 0.003). Three calls: the first X-step of the smoothing stage (start =
  truth + smooth error 0.02), the first of the final stage (lambda2 = 0, start = the exact smoothing-stage answer: the
  hardest call of a real solve) and a late one (start = the exact answer + smooth error 1e-4).

Measured: CPU seconds (time.process_time, median of `--repeats`; 1 BLAS thread unless `--threads`), CG iterations
(a batched block-Jacobi CG, or the Jacobi + two-level iterations of the reverted two-level X-step at bfb8730), and
the largest point error against a direct solve (one sparse LU per point) relative to the scene size (the largest
|coordinate| of the reference).
The baseline is `reconstruct/solver/xstep.py` at `--baseline` (git show), loaded as a separate module.
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import module_at_revision, solver_version
from long_capture import long_problem

import reconstruct.solver.xstep as current

log = logging.getLogger("xstep_speed")


@dataclass
class Call:
    W: sp.csc_matrix
    centers: np.ndarray
    rays: np.ndarray
    video_index: np.ndarray
    lambda2: float
    start: np.ndarray | None
    label: str


# ------------------------------------------------------------------------------------------------------------
# Inputs


def recorded_calls(frames: int) -> list[Call]:
    """Every X-step of a default full solve."""
    import reconstruct.solver.alternation as solver

    if frames == 700:
        from solver_speed import capture_of

        _, problem = capture_of(frames)
    else:
        _, problem = long_problem(frames)
    calls: list[Call] = []
    original = solver.solve_x

    def recording(
        W: Any, centers: np.ndarray, rays: np.ndarray, video_index: np.ndarray, options: Any, **kwargs: Any
    ) -> np.ndarray:
        start = kwargs.get("start")
        calls.append(
            Call(
                W=W.copy(),
                centers=centers,
                rays=rays,
                video_index=video_index,
                lambda2=options.lambda2,
                start=None if start is None else start.copy(),
                label=f"#{len(calls)}",
            )
        )
        return original(W, centers, rays, video_index, options, **kwargs)

    solver.solve_x = recording
    try:
        solver.solve(problem, solver.SolverOptions())
    finally:
        solver.solve_x = original
    return calls


def smooth_error(times: np.ndarray, P: int, scale: float, width: int, rng: np.random.Generator) -> np.ndarray:
    """(F, P, 3) Gaussian-filtered noise along the true time order, RMS `scale`, correlation ~`width` captures."""
    F = len(times)
    noise = rng.normal(size=(F + 4 * width, P * 3))
    kernel = np.exp(-0.5 * (np.arange(-2 * width, 2 * width + 1) / width) ** 2)
    kernel /= np.sqrt(np.sum(kernel**2))
    filtered = np.stack([np.convolve(noise[:, k], kernel, mode="valid")[:F] for k in range(P * 3)], axis=1)
    out = np.empty((F, P * 3))
    out[np.argsort(times)] = scale * filtered
    return out.reshape(F, P, 3)


def synthetic_calls(frames: int, seed: int = 0) -> list[Call]:
    from reconstruct.solver.candidates import VideoLayout, window_pool
    from reconstruct.solver.rays import camera_normalization, viewing_rays
    from reconstruct.solver.wstep import WStepOptions, solve_w

    capture, problem = long_problem(frames)
    rows = capture.truth.index()
    order = np.array(
        [rows[(problem.video_names[v], int(f))] for v, f in zip(problem.video_index, problem.frames, strict=True)]
    )
    video_index = problem.video_index
    rays = viewing_rays(problem)
    normalization = camera_normalization(problem.centers, video_index)
    centers = normalization.apply(problem.centers)
    truth = normalization.apply(capture.truth.xyz[order])
    times = capture.truth.extra["time"][order, 0]
    F, P = truth.shape[:2]
    rng = np.random.default_rng(seed)
    layout = VideoLayout.of(video_index)
    anchor = np.zeros((F, len(layout.starts)), dtype=int)
    for b, (first, length) in enumerate(zip(layout.starts, layout.lengths, strict=True)):
        anchor[:, b] = np.clip(np.searchsorted(times[first : first + length], times), 0, length - 1)
    shapes = truth + smooth_error(times, P, 0.003, 20, rng)
    W, _ = solve_w(
        shapes.reshape(F, -1),
        video_index,
        P,
        WStepOptions(full_kkt_check=False),
        pool=window_pool(anchor, video_index, layout, 12),
    )
    W_csc = W.to_csc()

    def exact(lambda2: float, start: np.ndarray) -> np.ndarray:
        return reference(
            Call(W=W_csc, centers=centers, rays=rays, video_index=video_index, lambda2=lambda2, start=start, label="")
        )

    start = truth + smooth_error(times, P, 0.02, 40, rng) + 0.003 * rng.normal(size=truth.shape)
    smooth = exact(0.1, start)
    final = exact(0.0, smooth)
    late = final + smooth_error(times, P, 1e-4, 40, rng)
    common = {"W": W_csc, "centers": centers, "rays": rays, "video_index": video_index}
    return [
        Call(**common, lambda2=0.1, start=start, label="smooth, first"),
        Call(**common, lambda2=0.0, start=smooth, label="final, first"),
        Call(**common, lambda2=0.0, start=late, label="final, late"),
    ]


# ------------------------------------------------------------------------------------------------------------
# Measurement


def baseline_module(revision: str) -> ModuleType:
    return module_at_revision("reconstruct/solver/xstep.py", revision, "xstep_baseline")


class IterationCounter:
    """CG iterations of one solve_x call: of the function `_batched_cg`, or of the class `_BatchedCG` of the reverted
    two-level X-step (Jacobi and two-level iterations apart)."""

    def __init__(self, module: ModuleType):
        self.counts = {"jacobi": 0, "two-level": 0}
        if hasattr(module, "_BatchedCG"):
            run = module._BatchedCG.run
            counts = self.counts

            def counting_run(cg: Any, iterations: int) -> None:
                before = cg.iterations
                run(cg, iterations)
                kind = "two-level" if "two_level" in cg.precondition.__qualname__ else "jacobi"
                counts[kind] += cg.iterations - before

            module._BatchedCG.run = counting_run
        else:
            batched = module._batched_cg
            # Revisions whose CG drops converged points from its batch take operators(points) -> (apply,
            # precondition), rebuilt at each drop; older ones take apply and precondition themselves.
            takes_operators = next(iter(inspect.signature(batched).parameters)) == "operators"

            def counting_cg(first: Any, *args: Any, **kwargs: Any) -> Any:
                applied = [0]

                def counted(apply: Any) -> Any:
                    def application(*operands: np.ndarray) -> Any:  # apply(v) or apply(Y, out), by revision
                        applied[0] += 1
                        return apply(*operands)

                    return application

                def counting_operators(points: np.ndarray) -> Any:
                    apply, precondition = first(points)
                    return counted(apply), precondition

                result = batched(counting_operators if takes_operators else counted(first), *args, **kwargs)
                self.counts["jacobi"] += applied[0] - 1  # one application computes the initial residual
                return result

            setattr(module, "_batched_cg", counting_cg)  # noqa: B010 (ModuleType has no such attribute to mypy)

    def reset(self) -> None:
        for key in self.counts:
            self.counts[key] = 0


def reference(call: Call) -> np.ndarray:
    """The X-step solved directly: one sparse LU per point (the X-step's own fallback), default lambda3."""
    F, P = call.rays.shape[:2]
    options = current.XStepOptions(lambda2=call.lambda2)
    Q3 = sp.kron(current.quadratic_form(call.W, call.video_index, P, call.lambda2), sp.identity(3), format="csr")
    observed = ~np.isnan(call.rays[..., 0])
    weight = options.lambda3 / (F * P)
    return np.stack(
        [current._solve_soft(Q3, call.centers, call.rays[:, p], observed[:, p], weight) for p in range(P)], axis=1
    )


def measure(
    module: ModuleType, counter: IterationCounter, calls: list[Call], repeats: int, references: list[np.ndarray]
) -> list[dict[str, Any]]:
    out = []
    for call, ref in zip(calls, references, strict=True):
        times = []
        for _ in range(repeats):
            counter.reset()
            started = time.process_time()
            points = module.solve_x(
                call.W,
                call.centers,
                call.rays,
                call.video_index,
                module.XStepOptions(lambda2=call.lambda2),
                start=call.start,
            )
            times.append(time.process_time() - started)
        out.append(
            {
                "label": call.label,
                "cpu_s": statistics.median(times),
                **counter.counts,
                "error": float(np.abs(points - ref).max() / np.abs(ref).max()),
            }
        )
    return out


def run_size(
    kind: str, frames: int, baseline: ModuleType, counters: dict[str, IterationCounter], repeats: int
) -> dict[str, Any]:
    started = time.perf_counter()
    calls = recorded_calls(frames) if kind == "real" else synthetic_calls(frames)
    log.info("F = %d (%s): %d calls prepared in %.0f s", frames, kind, len(calls), time.perf_counter() - started)
    references = [reference(call) for call in calls]
    return {
        "kind": kind,
        "frames": int(calls[0].rays.shape[0]),
        "points": int(calls[0].rays.shape[1]),
        "baseline": measure(baseline, counters["baseline"], calls, repeats, references),
        "current": measure(current, counters["current"], calls, repeats, references),
    }


def print_tables(results: list[dict[str, Any]], revision: str) -> None:
    print(f"\nsolver {solver_version()}; baseline xstep.py at {revision}; CPU s per call (median of repeats)\n")
    print(
        "| F | P | input | X-steps | baseline CPU s (total / per call) | current CPU s | speed-up | "
        "baseline CG its (mean / max) | current Jacobi + two-level its (mean / max) | max error baseline / current |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        b, c = r["baseline"], r["current"]
        tb, tc = sum(x["cpu_s"] for x in b), sum(x["cpu_s"] for x in c)
        ib = [x["jacobi"] for x in b]
        ic = [x["jacobi"] + x["two-level"] for x in c]
        print(
            f"| {r['frames']} | {r['points']} | {r['kind']} | {len(b)} | {tb:.2f} / {tb / len(b):.3f} | "
            f"{tc:.2f} / {tc / len(c):.3f} | {tb / tc:.1f}x | {np.mean(ib):.0f} / {max(ib)} | "
            f"{np.mean([x['jacobi'] for x in c]):.0f} + {np.mean([x['two-level'] for x in c]):.1f} / {max(ic)} | "
            f"{max(x['error'] for x in b):.0e} / {max(x['error'] for x in c):.0e} |"
        )
    print("\nSynthetic calls one by one:\n")
    print("| F | call | baseline its | baseline s | current its (Jacobi + two-level) | current s |")
    print("|---|---|---|---|---|---|")
    for r in results:
        if r["kind"] != "synthetic":
            continue
        for b, c in zip(r["baseline"], r["current"], strict=True):
            print(
                f"| {r['frames']} | {b['label']} | {b['jacobi']} | {b['cpu_s']:.3f} | "
                f"{c['jacobi']} + {c['two-level']} | {c['cpu_s']:.3f} |"
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--real", default="700,2000", help="F of recorded full solves ('' for none)")
    parser.add_argument("--synthetic", default="5000,20000", help="F of synthetic calls ('' for none)")
    parser.add_argument("--baseline", default="6eeb4a6", help="git revision of the baseline X-step")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="BLAS threads (threadpoolctl)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from threadpoolctl import threadpool_limits

    threadpool_limits(args.threads)
    baseline = baseline_module(args.baseline)
    counters = {"baseline": IterationCounter(baseline), "current": IterationCounter(current)}
    sizes = [("real", int(s)) for s in args.real.split(",") if s] + [
        ("synthetic", int(s)) for s in args.synthetic.split(",") if s
    ]
    results = []
    for kind, frames in sizes:
        results.append(run_size(kind, frames, baseline, counters, args.repeats))
        if args.json:
            args.json.write_text(
                json.dumps(
                    {
                        "solver": solver_version(),
                        "baseline": args.baseline,
                        "threads": args.threads,
                        "results": results,
                    },
                    indent=1,
                )
            )
    print_tables(results, args.baseline)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
