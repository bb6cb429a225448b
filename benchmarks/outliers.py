"""One false detection anywhere (issue 18): the default `dynrecon solve` with 1 % of its observations moved to
uniformly random pixels of the image, against the same capture without them.

    nice python benchmarks/outliers.py [--windows hdm05,cmu-jumps,squat] [--fraction 0.01] [--work DIR]

Per mocap window (the paper's protocol, `dynrecon simulate`, decoder times given) and setting (noise-free; 1 px):
the share of points within 10 mm of the truth without and with the false detections, their difference in
percentage points (the target: at most 1), and how many of the points that moved by more than 10 mm belong to a
frame that holds a false detection (the rest were moved by a false detection elsewhere). Everything through the
CLI, as a user runs it. Needs the mocap files of ../shared (exits with a message otherwise).
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from common import WINDOWS, require_mocap_dir

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon
from reconstruct.outputs.points import FramePoints, read_points
from sfm.cameras import read_cameras
from simulation.evaluate import ReconstructionAccuracy, evaluate

SETTINGS = {"clean": [], "1px": ["--noise", "1"]}
RATE = 120.0  # the paper protocol's windows are 120 Hz files


def inject(
    source: Path, target: Path, sizes: dict[str, tuple[int, int]], fraction: float, seed: int
) -> tuple[int, set[tuple[str, int]]]:
    """Copy tracks.csv with `fraction` of its rows moved to uniform random pixels; returns how many rows, and
    their (video, frame)."""
    rng = np.random.default_rng(seed)
    with source.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        fields = list(reader.fieldnames or [])
        rows = list(reader)
    chosen = rng.choice(len(rows), size=max(1, round(fraction * len(rows))), replace=False)
    hit = set()
    for index in chosen:
        row = rows[index]
        width, height = sizes[row["video"]]
        row["x"], row["y"] = f"{rng.uniform(0, width):.3f}", f"{rng.uniform(0, height):.3f}"
        hit.add((row["video"], int(row["frame"])))
    with target.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return len(chosen), hit


def accuracy(ws: Path, truth: FramePoints) -> ReconstructionAccuracy:
    """`dynrecon evaluate`'s numbers for ws/points3d.csv; its `errors` follow the truth's rows, so two solves of
    the same capture compare element by element."""
    return evaluate(read_points(ws / "points3d.csv"), truth)


def scored_frames(truth: FramePoints) -> list[tuple[str, int]]:
    """(video, frame) of each element of `ReconstructionAccuracy.errors`, in its order."""
    rows, _ = np.nonzero(np.isfinite(truth.xyz).all(axis=2))
    return [(truth.videos[r], int(truth.frames[r])) for r in rows]


def run(window_name: str, setting: str, fraction: float, work: Path) -> dict:
    window = next(w for w in WINDOWS if w.name == window_name)
    base = work / f"{window_name}-{setting}"
    shutil.rmtree(base, ignore_errors=True)
    clean, dirty = base / "clean", base / "outliers"
    args = ["simulate", str(require_mocap_dir() / window.path), "--out", str(clean), *SETTINGS[setting]]
    args += ["--start", str(round(window.start_s * RATE)), "--length", str(round(window.seconds * RATE))]
    assert dynrecon(["-q", *args]) == 0
    shutil.copytree(clean, dirty)
    sizes = {v.name: (v.width, v.height) for v in read_cameras(clean / "cameras.json").videos}
    count, hit = inject(clean / "tracks.csv", dirty / "tracks.csv", sizes, fraction, seed=WINDOWS.index(window))
    seconds = {}
    for ws in (clean, dirty):
        started = time.perf_counter()
        solve = ["-q", "solve", "--cameras", str(ws / "cameras.json"), "--tracks", str(ws / "tracks.csv")]
        assert dynrecon([*solve, "--out", str(ws), "--no-recording"]) == 0
        seconds[ws.name] = time.perf_counter() - started
    truth = read_points(clean / "truth.csv")
    before, after = accuracy(clean, truth), accuracy(dirty, truth)
    lost = np.flatnonzero((before.errors < 10.0) & ~(after.errors < 10.0))
    frames = scored_frames(truth)
    report = json.loads((dirty / "report.json").read_text(encoding="utf-8"))
    return {
        "window": window_name,
        "setting": setting,
        "false_rows": count,
        "hit_frames": len(hit),
        "clean": float(before.share_under[0]),
        "outliers": float(after.share_under[0]),
        "points": before.count,
        "lost": len(lost),
        "lost_in_hit_frames": sum(frames[i] in hit for i in lost),
        "path": (report.get("temporal") or {}).get("path", report.get("path")),
        "seconds": seconds,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--windows", default="hdm05,cmu-jumps,squat")
    parser.add_argument("--settings", default="clean,1px")
    parser.add_argument("--fraction", type=float, default=0.01)
    parser.add_argument("--work", type=Path, default=Path("/tmp/outliers"))
    args = parser.parse_args()
    rows = []
    print(
        "| window | setting | false rows (frames) | < 10 mm without | with | difference (pp) | points lost "
        "| of them in a hit frame |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in args.windows.split(","):
        for setting in args.settings.split(","):
            row = run(name, setting, args.fraction, args.work)
            rows.append(row)
            print(
                f"| {name} | {setting} | {row['false_rows']} ({row['hit_frames']}) | {100 * row['clean']:.2f} % | "
                f"{100 * row['outliers']:.2f} % | {100 * (row['clean'] - row['outliers']):.2f} | {row['lost']} | "
                f"{row['lost_in_hit_frames']} |",
                flush=True,
            )
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
