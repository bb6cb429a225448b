"""A few tracked points cut from motion capture (issue 22: P = 1, 2, 5), through the whole `dynrecon solve`.

    python benchmarks/few_points.py [--points 1,2,5] [--cases DIR] [--timeout 600] [--json OUT]

Data: `dynrecon simulate --mode phones` (4 videos on their own clocks at 30, 25, 59.94 and 24 fps, decoder times in
cameras.json) on CMU 01_01 and complexknee 2022_01_0401, cut to about 5 s (F ~ 700). From each capture, P points
are kept (tracks.csv and truth.csv cut alike): the P markers that travel farthest, the ones a user would track on
a ball or a limb. Each cut is solved as a subprocess (`--no-recording`; the process time counts imports and file
reading) and scored with `dynrecon evaluate`. The table gives per case the process time, the path report.json
names (`temporal.path`), the stage times, and the share of points within 10 mm and the median error. The same
capture with all its points is the reference row.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MOCAP = ROOT.parent / "shared" / "data" / "mocap"
FILES = {"cmu": ("cmu/cmu_01_01.c3d", 120.0), "complexknee": ("lab/complexknee/2022_01_0401.c3d", 100.0)}
SECONDS = 5.0


def dynrecon(args: list[str], timeout: float) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "dynrecon", "-q", *args],
        check=True,
        timeout=timeout,
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    return time.perf_counter() - start, done.stdout


def simulate(name: str, folder: Path) -> None:
    if (folder / "tracks.csv").exists():
        return
    path, rate = FILES[name]
    args = ["simulate", str(MOCAP / path), "--mode", "phones", "--cameras", "4", "--length", str(int(SECONDS * rate))]
    dynrecon([*args, "--out", str(folder)], 600)


def farthest(folder: Path, count: int) -> list[str]:
    """The `count` points whose true trajectory is longest (summed over the first video's frames)."""
    paths: dict[str, list[np.ndarray]] = {}
    with (folder / "truth.csv").open(newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if r["video"] == "cam0"]
    for r in sorted(rows, key=lambda r: int(r["frame"])):
        paths.setdefault(r["point"], []).append(np.array([float(r["x"]), float(r["y"]), float(r["z"])]))
    length = {p: float(np.nansum(np.linalg.norm(np.diff(np.array(v), axis=0), axis=1))) for p, v in paths.items()}
    return sorted(length, key=lambda p: -length[p])[:count]


def cut(source: Path, folder: Path, keep: list[str]) -> None:
    """A copy of the capture with only the `keep` points in tracks.csv and truth.csv."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("cameras.json", "simulation.json", "clocks_truth.json"):
        if (source / name).exists():
            (folder / name).write_bytes((source / name).read_bytes())
    for name in ("tracks.csv", "truth.csv"):
        with (source / name).open(newline="") as handle, (folder / name).open("w", newline="") as out:
            reader = csv.DictReader(handle)
            writer = csv.DictWriter(out, fieldnames=reader.fieldnames or [])
            writer.writeheader()
            writer.writerows(r for r in reader if r["point"] in keep)


def solve(folder: Path, timeout: float) -> dict[str, object]:
    cmd = ["solve", "--cameras", str(folder / "cameras.json"), "--tracks", str(folder / "tracks.csv")]
    try:
        seconds, _ = dynrecon([*cmd, "--out", str(folder / "out"), "--no-recording"], timeout)
    except subprocess.TimeoutExpired:
        return {"process_s": float("inf"), "path": "timeout"}
    report = json.loads((folder / "out" / "report.json").read_text())
    _, scored = dynrecon(["evaluate", str(folder / "out"), "--truth", str(folder / "truth.csv"), "--json"], 300)
    accuracy = json.loads(scored)
    return {
        "process_s": seconds,
        "F": report["size"]["frames"],
        "P": report["size"].get("points"),
        "path": report["temporal"].get("path"),
        "timings": report["timings"],
        "median_mm": accuracy["median"],
        "within_10mm": accuracy["share_under"][accuracy["thresholds"].index(10.0)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", default="1,2,5", help="points kept, comma-separated")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per solve")
    parser.add_argument("--cases", type=Path, help="keep the simulated captures here and reuse them")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    if not MOCAP.is_dir():
        sys.exit(f"needs the motion capture in {MOCAP} (../shared)")
    rows: dict[str, dict[str, object]] = {}
    with contextlib.ExitStack() as stack:
        base = args.cases or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        for name in FILES:
            source = base / f"{name}-{SECONDS:g}s"
            simulate(name, source)
            for count in [int(c) for c in args.points.split(",")]:
                keep = farthest(source, count)
                folder = base / f"{name}-{SECONDS:g}s-P{count}"
                cut(source, folder, keep)
                rows[f"{name} P={count}"] = {**solve(folder, args.timeout), "points": keep}
                print(f"{name} P={count}", json.dumps(rows[f"{name} P={count}"]), flush=True)
            rows[f"{name} all"] = solve(source, args.timeout)
            print(f"{name} all", json.dumps(rows[f"{name} all"]), flush=True)
    print("\n| case | F | P | process s | solver s | clocks s | refinement s | path | < 10 mm | median mm |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for case, r in rows.items():
        t = r.get("timings", {})
        assert isinstance(t, dict)
        within = r.get("within_10mm")
        print(
            f"| {case} | {r.get('F', '')} | {r.get('P', '')} | {float(r['process_s']):.1f} | "  # type: ignore[arg-type]
            f"{t.get('total', float('nan')):.2f} | {t.get('clocks', float('nan')):.2f} | "
            f"{t.get('refinement', float('nan')):.2f} | {r['path']} | "
            f"{'' if within is None else f'{100 * float(within):.1f} %'} | "  # type: ignore[arg-type]
            f"{float(r.get('median_mm', float('nan'))):.1f} |"  # type: ignore[arg-type]
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
