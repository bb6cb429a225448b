"""Tracking accuracy on rendered videos with known 2D positions, labels on 1 frame in N.

For each scenario (textured markers over a textured background, camera pan/roll/zoom, motion blur, an
occluding bar; lossless FFV1 or lossy mp4v), every combination of step method and blend is run on the same
decoded video and scored on the frames that carry no label: median / 95th percentile / max pixel error where
the marker is visible, the share of visible frames that got a position (coverage), and the share of hidden
frames (occluded or outside the picture) where the tracker correctly gave up.

    python benchmarks/tracking_accuracy.py [--every 10] [--frames 80] [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tracking.accuracy import labels_every, score
from tracking.frames import VideoFrames
from tracking.options import Blend, Method, TrackOptions
from tracking.propagate import track_video
from tracking.synthetic import SyntheticOptions, render_video

MODERATE: dict[str, Any] = {"speed": 3.0, "pan": 1.5, "exposure": 0.6, "rotation_deg": 3.0}
FAST: dict[str, Any] = {"speed": 8.0, "pan": 4.0, "exposure": 1.0, "rotation_deg": 6.0}
JUMPY: dict[str, Any] = {"speed": 20.0, "pan": 6.0, "exposure": 0.3, "rotation_deg": 6.0}
SCENARIOS = {
    "moderate, FFV1": (MODERATE, "FFV1", ".avi"),
    "moderate, mp4v": (MODERATE, "mp4v", ".mp4"),
    "fast + long blur, FFV1": (FAST, "FFV1", ".avi"),
    "fast + long blur, mp4v": (FAST, "mp4v", ".mp4"),
    "large jumps, mp4v": (JUMPY, "mp4v", ".mp4"),
    "fast + auto-exposure flicker, mp4v": ({**FAST, "flicker": 0.15}, "mp4v", ".mp4"),
}
VARIANTS = [
    ("lk", TrackOptions(method=Method.LK, blend=Blend.FORWARD)),
    ("lk", TrackOptions(method=Method.LK, blend=Blend.BEST)),
    ("lk", TrackOptions(method=Method.LK, blend=Blend.WEIGHTED)),
    ("lk, no brightness normalization", TrackOptions(method=Method.LK, blend=Blend.WEIGHTED, normalize=False)),
    ("lk, no score memory", TrackOptions(method=Method.LK, blend=Blend.WEIGHTED, score_memory=False)),
    ("lk, no closure check", TrackOptions(method=Method.LK, blend=Blend.WEIGHTED, closure_check=False)),
    ("lk+csrt", TrackOptions(method=Method.LK_CSRT, blend=Blend.WEIGHTED)),
    ("lk+csrt, unrefined kept", TrackOptions(method=Method.LK_CSRT, blend=Blend.WEIGHTED, accept_unrefined=True)),
    ("csrt", TrackOptions(method=Method.CSRT, blend=Blend.WEIGHTED)),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--every", type=int, default=10, help="label 1 frame in N (default 10)")
    parser.add_argument("--frames", type=int, default=80)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--quick", action="store_true", help="one scenario, no CSRT-only variant")
    parser.add_argument("--default-only", action="store_true", help="only the default TrackOptions()")
    parser.add_argument(
        "--csrt-everywhere",
        action="store_true",
        help="run the slow CSRT-only variant on every scenario, not only the first",
    )
    parser.add_argument("--out-dir", type=Path, help="keep the rendered videos here")
    args = parser.parse_args()
    scenarios = dict(list(SCENARIOS.items())[:1]) if args.quick else SCENARIOS
    variants = [v for v in VARIANTS if not (args.quick and v[1].method is Method.CSRT)]
    if args.default_only:
        variants = [("default", TrackOptions())]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out_dir or Path(tmp)
        print(f"{args.width}x{args.height}, {args.frames} frames, 8 markers, labels on 1 frame in {args.every}\n")
        print("| scenario | method | blend | median px | p95 px | max px | coverage | gave up when hidden | s |")
        print("|---|---|---|---|---|---|---|---|---|")
        for seed, (name, (motion, fourcc, suffix)) in enumerate(scenarios.items()):
            path = folder / f"scenario{seed}{suffix}"
            video = render_video(
                path,
                SyntheticOptions(
                    width=args.width, height=args.height, frames=args.frames, fourcc=fourcc, seed=seed, **motion
                ),
            )
            frames = VideoFrames(path)
            labels = labels_every(video, args.every)
            for label, options in variants:
                if options.method is Method.CSRT and seed > 0 and not args.csrt_everywhere:
                    continue
                start = time.perf_counter()
                result = track_video(frames, labels, options)
                seconds = time.perf_counter() - start
                print(
                    f"| {name} | {label} | {options.blend.value} | {score(result, video).row()} | {seconds:.1f} |",
                    flush=True,
                )
            frames.close()


if __name__ == "__main__":
    main()
