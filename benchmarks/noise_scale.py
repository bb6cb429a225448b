"""The subject path's noise scale (`sfm.subject.choose_noise`) on synthetic rigs with known truth.

    python benchmarks/noise_scale.py [--seeds 2,3,4] [--cases 0.7/0,5/0,3/3,4/4]

Each case (`noise/bias` in pixels: per-observation scatter, and a constant shift per camera and point, as a pose
detector's joint centre has) is a 4-camera skeleton rig (10 s, 3 % false detections, known intrinsics) solved at
every scale of NOISE_SCALES_PX by `choose_scale` (as `register` does); the table gives each scale's worst rotation
error (deg) and centre error (% of the camera spread) against the truth, the folds' rotation change (median over
the cameras) and how many cameras they keep, the scale kept, and whether it was the better one for the user: more
stable cameras (the others are refused), then the smaller rotation error.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm.subject import SubjectOptions, SubjectResult, SubjectVideo, calibrate_from_subject
from sfm.subject.model import NOISE_SCALES_PX
from sfm.subject.noise import choose_scale
from sfm.subject.stability import Stability, check_stability
from sfm.subject.synthetic import compare, make_rig
from tracking.tracks import Tracks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="2,3,4")
    parser.add_argument("--cases", default="0.7/0,5/0,3/3,4/4")
    args = parser.parse_args(argv)
    scales = " | ".join(f"{px:g} px: rot / centre / folds" for px in NOISE_SCALES_PX)
    print(f"| noise / bias px | seed | {scales} | kept | kept the better |")
    print("|---|---|" + "---|" * len(NOISE_SCALES_PX) + "---|---|")
    right = total = 0
    for case in args.cases.split(","):
        noise, bias = (float(v) for v in case.split("/"))
        for seed in (int(s) for s in args.seeds.split(",")):
            tracks, videos, truth = make_rig(
                kind="skeleton", n_cameras=4, duration=10.0, noise_px=noise, bias_px=bias, false_rate=0.03, seed=seed
            )
            solved: dict[float, SubjectResult] = {}

            def trial(
                scaled: SubjectOptions,
                tracks: Tracks = tracks,
                videos: list[SubjectVideo] = videos,
                solved: dict[float, SubjectResult] = solved,
            ) -> tuple[SubjectResult, Stability, None]:
                result = calibrate_from_subject(tracks, videos, scaled)
                solved[float(scaled.inlier_px or 0.0)] = result
                return result, check_stability(tracks, videos, result, scaled), None

            chosen = choose_scale(trial, SubjectOptions())[0]
            cells, outcome = [], {}
            for px in NOISE_SCALES_PX:
                if px not in solved:
                    cells.append("failed")
                    continue
                err = compare(solved[px], truth)
                folds = chosen.noise_check[px]
                # what the user gets: the unstable cameras are refused, so fewer stable ones is worse
                outcome[px] = (-folds.stable, err.rotation_deg)
                cells.append(
                    f"{err.rotation_deg:.2f} / {err.centre_pct:.2f} / {folds.fold_rotation_deg:.2f}"
                    f" ({folds.stable} of {err.posed} stable)"
                )
            kept = chosen.inlier_px
            better = min(outcome, key=lambda px: outcome[px]) if outcome else None
            total += 1
            right += int(kept == better)
            print(f"| {noise:g} / {bias:g} | {seed} | {' | '.join(cells)} | {kept:g} | {kept == better} |")
    print(f"\nkept the better scale in {right} of {total} rigs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
