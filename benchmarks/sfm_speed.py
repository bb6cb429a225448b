"""Speed of `register` per stage: 3 synthetic videos x N frames at 1280x720 (long side 1280).

    python benchmarks/sfm_speed.py [--frames 100] [--sfm-frames 30] [--mapper incremental] [--out /tmp/sfm_speed]

`--sfm-frames` of each video go through SfM (extract, match, map); all other frames are posed by PnP against the
model (localize). Prints the stage timings, the time per registered frame for both kinds, and the number of frames
a user can expect to register in 10 minutes on this machine. Videos are rendered once and reused.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm import Localize, Mapper, RegisterOptions
from sfm import register as run
from sfm.synthetic.demo import render_demo, three_cameras


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--sfm-frames", type=int, default=30)
    parser.add_argument("--mapper", default="incremental")
    parser.add_argument("--out", type=Path, default=Path("/tmp/sfm_speed"))
    args = parser.parse_args()
    videos_dir = args.out / f"videos_{args.frames}"
    paths = [videos_dir / f"cam{i}.mp4" for i in range(3)]
    if not all(p.exists() for p in paths):
        started = time.perf_counter()
        render_demo(videos_dir, three_cameras(1280, 720, frames=(args.frames,) * 3))
        print(f"rendered {3 * args.frames} frames at 1280x720 in {time.perf_counter() - started:.0f} s")
    ws = args.out / "ws"
    shutil.rmtree(ws, ignore_errors=True)
    options = RegisterOptions(
        max_frames=args.sfm_frames, long_side=1280, mapper=Mapper(args.mapper), localize=Localize.ALL
    )
    started = time.perf_counter()
    run(paths, ws, options)
    total = time.perf_counter() - started
    report = json.loads((ws / "register_report.json").read_text())
    t = report["timings_s"]
    sfm = sum(v["registered_by_sfm"] for v in report["videos"])
    pnp = sum(v["registered_by_pnp"] for v in report["videos"])
    given = sum(v["frames_given"] for v in report["videos"])
    print(f"cores: {os.cpu_count()}, load average at the end: {os.getloadavg()[0]:.1f}")
    print("| stage | seconds | per frame (s) |")
    print("|---|---|---|")
    for stage, count in (
        ("probe", given),
        ("decode", 3 * args.sfm_frames),
        ("extract", sfm),
        ("match", sfm),
        ("map", sfm),
        ("localize", pnp),
        ("export", given),
    ):
        print(f"| {stage} | {t.get(stage, 0):.1f} | {t.get(stage, 0) / max(count, 1):.3f} |")
    sfm_cost = (t["extract"] + t["match"] + t["map"]) / max(sfm, 1)
    pnp_cost = t["localize"] / max(pnp, 1)
    print(
        f"registered {sfm + pnp}/{given} frames ({sfm} by SfM, {pnp} by PnP) in {total:.0f} s: "
        f"{total / max(sfm + pnp, 1):.2f} s per registered frame; SfM {sfm_cost:.2f} s/frame, PnP "
        f"{pnp_cost:.2f} s/frame"
    )
    ratio = args.sfm_frames / args.frames
    per_frame = ratio * sfm_cost + (1 - ratio) * pnp_cost
    print(f"10-minute budget at this SfM share ({ratio:.0%}): about {600 / per_frame:.0f} frames")


if __name__ == "__main__":
    main()
