"""A track search locked on another cycle: what `temporal.recover_and_refine` does when one video's clock from the
tracks is off by whole frame periods and kept against W's links (the links' clocks as a second hypothesis,
reconstruct/temporal.py `_tracks_or_links`).

    python benchmarks/wrong_cycle.py [--periods 0,2,30] [--frames 240] [--points 8] [--noise 1]

The paper's protocol on mocap (tests/synthetic_motion.py), each video's decoder clock restarted at its first frame
(the offsets are unknown), the seed solve once; then per shift the track search's clock of one video is moved by
that many of its frame periods before the clocks are combined. Printed per shift: the path, which clock was kept
and both predicted errors (GCV) and residuals (report.json `temporal.links_clocks`), and the median / p90 3D error
against the truth.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from synthetic_motion import synthetic_problem, truth_array  # noqa: E402

import reconstruct.clocks.estimate as estimate  # noqa: E402
from reconstruct.solver.alternation import solve  # noqa: E402
from reconstruct.temporal import recover_and_refine  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--periods", default="0,2,30", help="shifts of one video's track clock, in frame periods")
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--points", type=int, default=8)
    parser.add_argument("--noise", type=float, default=1.0, help="pixels")
    args = parser.parse_args()

    problem, truth = synthetic_problem(frames=args.frames, points=args.points, noise_px=args.noise)
    starts = np.array([problem.times[problem.video_index == v].min() for v in range(len(problem.video_names))])
    problem.times = problem.times - starts[problem.video_index]
    seed = solve(problem)
    expected = truth_array(problem, truth)
    search = estimate.search_clocks

    def error_mm(points: np.ndarray) -> str:
        e = np.linalg.norm(points - expected, axis=-1)
        e = e[np.isfinite(e)]
        return f"{np.median(e):.2f} / {np.percentile(e, 90):.2f}"

    print(f"seed solve: {error_mm(seed.points)} mm (median / p90)\n")
    print(
        "| track clock moved (periods) | path | kept | predicted (residual) tracks / links (px) "
        "| error median / p90 (mm) |"
    )
    print("|---|---|---|---|---|")
    for periods in (float(p) for p in args.periods.split(",")):

        def moved(problem, own, ref, *rest, periods=periods, **kwargs):  # type: ignore[no-untyped-def]
            found = copy.deepcopy(search(problem, own, ref, *rest, **kwargs))
            v = (ref + 1) % len(problem.video_names)
            found.params.coef[v][0] += periods * np.median(np.diff(np.sort(own[problem.video_index == v])))
            return found

        estimate.search_clocks = moved
        try:
            temporal = recover_and_refine(problem, seed)
        finally:
            estimate.search_clocks = search
        entry = temporal.report.get("links_clocks")
        kept = entry["kept"] if entry else "tracks (no disagreement)"
        residual = (
            f"{entry['predicted_px']['tracks']:.3g} / {entry['predicted_px']['links']:.3g} "
            f"({entry['residual_px']['tracks']:.3g} / {entry['residual_px']['links']:.3g})"
            if entry
            else ""
        )
        print(f"| {periods:g} | {temporal.report['path']} | {kept} | {residual} | {error_mm(temporal.points)} |")


if __name__ == "__main__":
    main()
