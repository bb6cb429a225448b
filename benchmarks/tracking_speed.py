"""Tracking speed at 1920x1080: points x frames per second for LK and for the CSRT fallback.

A rendered 1080p video (textured markers, camera motion, blur) is decoded once into memory; then `track_video`
runs on it with labels on 1 frame in 10 (forward and backward sweeps and the blend, as `dynrecon track` does).
Throughput = points x frames of the video / wall time. The CSRT row runs CSRT on every step (what the fallback
costs per step where LK fails); decoding is timed separately.

    python benchmarks/tracking_speed.py [--frames 30] [--points 16 128]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tracking.accuracy import labels_every, score
from tracking.frames import ArrayFrames, VideoFrames
from tracking.options import Method, TrackOptions
from tracking.propagate import track_video
from tracking.synthetic import SyntheticOptions, SyntheticVideo, render_video


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--points", type=int, nargs="+", default=[16, 128])
    parser.add_argument("--csrt-frames", type=int, default=10, help="frames for the (slow) CSRT rows")
    args = parser.parse_args()
    width, height = 1920, 1080
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "hd.mp4"
        start = time.perf_counter()
        video = render_video(
            path,
            SyntheticOptions(
                width=width,
                height=height,
                frames=args.frames,
                markers=16,
                marker_radius=24.0,
                speed=6.0,
                pan=3.0,
                blur_samples=2,
                fourcc="mp4v",
                seed=11,
            ),
        )
        render_s = time.perf_counter() - start
        start = time.perf_counter()
        decoded = VideoFrames(path, cache_bytes=4 << 30)
        gray = [decoded.gray(i) for i in range(len(decoded))]
        decode_s = time.perf_counter() - start
    print(
        f"{width}x{height}, {args.frames} frames (mp4v); render {render_s:.1f} s, "
        f"decode to gray {decode_s:.2f} s = {args.frames / decode_s:.0f} frames/s\n"
    )
    print("| method | points | frames | seconds | points x frames / s | positions out | median / p95 px (markers) |")
    print("|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    marker_labels = labels_every(video, 10)
    for method in (Method.LK, Method.LK_CSRT, Method.CSRT):
        frames = args.frames if method is not Method.CSRT else min(args.frames, args.csrt_frames)
        source = ArrayFrames(gray[:frames])
        for count in args.points:
            labels = {name: {f: xy for f, xy in marks.items() if f < frames} for name, marks in marker_labels.items()}
            labels = dict(list(labels.items())[:count])
            # More points than markers: extra points on the textured background (speed only, no ground truth).
            for k in range(count - len(labels)):
                xy = (float(rng.uniform(100, width - 100)), float(rng.uniform(100, height - 100)))
                labels[f"bg{k}"] = {0: xy}
            start = time.perf_counter()
            result = track_video(source, labels, TrackOptions(method=method))
            seconds = time.perf_counter() - start
            steps = sum(len(v) for v in result.values())
            print(
                f"| {method.value} | {count} | {frames} | {seconds:.2f} | {count * frames / seconds:,.0f} "
                f"| {steps} | {_accuracy(result, video, frames)} |",
                flush=True,
            )


def _accuracy(result: dict, video: SyntheticVideo, frames: int) -> str:
    """Median / p95 error of the markers' tracked positions on the first `frames` frames."""
    clipped = SyntheticVideo(path=None, names=video.names, uv=video.uv[:frames], visible=video.visible[:frames])
    accuracy = score({name: result[name] for name in video.names if name in result}, clipped)
    return f"{accuracy.median:.3f} / {accuracy.p95:.3f}"


if __name__ == "__main__":
    main()
