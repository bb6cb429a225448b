"""Accuracy of `register` on the synthetic room against ground truth: masks on/off, incremental vs global.

    python benchmarks/sfm_synthetic.py [--width 480 --height 360 --frames 10,8,6 --max-frames 6]
        [--configs masks,nomasks,global] [--out /tmp/sfm_synthetic]

Prints one markdown table row per configuration: registered frames, centre error (% of the room diagonal) and
rotation error after a similarity alignment, and stage timings. CPU heavy (renders and registers per configuration).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm import Mapper, RegisterOptions, RegistrationError
from sfm import register as run
from sfm.cameras import CameraSet, read_cameras
from sfm.evaluate import compare
from sfm.synthetic.demo import render_demo, sphere_tracks, three_cameras
from tracking.tracks import write_tracks

ROOM_DIAGONAL = float(np.linalg.norm([8.0, 6.0, 3.0]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--frames", default="10,8,6")
    parser.add_argument("--max-frames", type=int, default=6)
    parser.add_argument("--max-features", type=int, default=1500)
    parser.add_argument("--configs", default="masks,nomasks,global")
    parser.add_argument("--out", type=Path, default=Path("/tmp/sfm_synthetic"))
    args = parser.parse_args()
    frames = tuple(int(x) for x in args.frames.split(","))
    started = time.perf_counter()
    videos = render_demo(args.out / "videos", three_cameras(args.width, args.height, frames=frames))  # type: ignore[arg-type]
    print(f"rendered {sum(frames)} frames in {time.perf_counter() - started:.1f} s")
    truth = CameraSet(videos=[v.cameras for v in videos])
    tracks = sphere_tracks(videos)
    print(
        "| config | registered | centre err mean / max (% diag) | rot err mean / max (deg) | extract | match "
        "| map | localize | total |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for config in args.configs.split(","):
        ws = args.out / f"ws_{config}"
        shutil.rmtree(ws, ignore_errors=True)
        write_tracks(ws / "tracks.csv", tracks)
        options = RegisterOptions(
            long_side=max(args.width, args.height),
            max_frames=args.max_frames,
            max_features=args.max_features,
            mask_radius=70,
            use_masks=config != "nomasks",
            mapper=Mapper.GLOBAL if config == "global" else Mapper.INCREMENTAL,
        )
        started = time.perf_counter()
        try:
            path = run([v.path for v in videos], ws, options)
        except RegistrationError as error:
            print(f"| {config} | failed: {error} |")
            continue
        total = time.perf_counter() - started
        report = json.loads((ws / "register_report.json").read_text())
        timings = report["timings_s"]
        errors = compare(read_cameras(path), truth)
        registered = sum(v["registered"] for v in report["videos"])
        print(
            f"| {config} | {registered}/{truth.num_frames} "
            f"| {100 * errors.center_errors.mean() / ROOM_DIAGONAL:.3f} / "
            f"{100 * errors.center_errors.max() / ROOM_DIAGONAL:.3f} "
            f"| {errors.rotation_errors_deg.mean():.3f} / {errors.rotation_errors_deg.max():.3f} "
            f"| {timings['extract']:.1f} | {timings['match']:.1f} | {timings['map']:.1f} "
            f"| {timings['localize']:.1f} | {total:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
