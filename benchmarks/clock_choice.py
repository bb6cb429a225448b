"""Registration's offsets against the solve's clocks (reconstruct/registered_offsets.py): which is kept, by which
criterion, and what it costs in 3D error, on simulations where the truth is known.

    python benchmarks/clock_choice.py [--work /tmp/clock_choice] [--captures phones,cmu0,cmu1,hand3,flight4,two]

Captures (`dynrecon simulate`, written once under WORK): `phones` (the tests' three phones), `cmu0` / `cmu1`
(four static phones filming CMU 01_01, 2 px), `hand3` (the same, handheld), `flight4` (one drone, 5 cameras),
`two` (two static phones). Two kinds of case per capture, each registered offset written into cameras.json as
`clock_offset`:
- **solve wrong**: registration's offsets true; the solve's clocks of one video moved by 0.1 ... -0.5 s and the
  trajectories refined on them (no polish), then `prefer_registered_offsets` decides;
- **registration wrong**: the whole `solve` with one video's registered offset moved by 0.04 ... 0.13 s.
Printed per case: the criterion, both measures (held-out px or residual px), which was kept, and the median 3D error
of the kept answer (mm) against the truth. Needs ../shared (CMU 01_01) for the CMU captures.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from synthetic_motion import simulated_phones, truth_array  # noqa: E402

from dynrecon.cli import main as dynrecon_main  # noqa: E402
from reconstruct.clocks.registered import check_registered_clocks  # noqa: E402
from reconstruct.outputs.points import read_points  # noqa: E402
from reconstruct.registered_offsets import PATH, prefer_registered_offsets  # noqa: E402
from reconstruct.stage import Reconstruction, SolveOptions, solve  # noqa: E402
from reconstruct.temporal import Temporal  # noqa: E402
from reconstruct.trajectory import refine  # noqa: E402
from sfm.cameras import CameraSet, read_cameras  # noqa: E402

SHARED = Path(os.environ.get("DYNRECON_SHARED", ROOT.parent / "shared"))
CMU = SHARED / "data" / "mocap" / "cmu" / "cmu_01_01.c3d"
CAPTURES = {
    "phones": None,
    "cmu0": ["--mode", "phones", "--seed", "0", "--noise", "2", "--length", "1200", "--cameras", "4"],
    "cmu1": ["--mode", "phones", "--seed", "1", "--noise", "2", "--length", "1200", "--cameras", "4"],
    "hand3": ["--mode", "phones", "--handheld", "--seed", "3", "--noise", "2", "--length", "1200", "--cameras", "4"],
    "flight4": ["--mode", "flight", "--seed", "4", "--duration", "2"],
    "two": ["--mode", "phones", "--seed", "1", "--noise", "2", "--length", "1200", "--cameras", "2"],
}
SOLVE_SHIFTS = (0.1, 0.2, 0.3, 0.5, -0.5)
REGISTERED_SHIFTS = (0.04, 0.07, 0.1, 0.13)


def capture(name: str, work: Path) -> Path:
    """The simulation folder of `name` under `work`, simulated on first use."""
    if name == "phones":
        folder = work / "phones" / "sim"
        return folder if (folder / "tracks.csv").exists() else simulated_phones(work / "phones")
    folder = work / name
    if not (folder / "tracks.csv").exists():
        arguments = CAPTURES[name]
        source = [] if "flight" in arguments else [str(CMU)]
        if dynrecon_main(["-q", "simulate", *source, "--out", str(folder), *arguments]) != 0:
            raise SystemExit(f"simulating {name} failed")
    return folder


def cameras_with(sim: Path, moved: float) -> CameraSet:
    """The simulation's cameras with the true clock offsets registered, the second video's moved by `moved` s."""
    cameras = read_cameras(sim / "cameras.json")
    truth = {v["name"]: v["offset_s"] for v in json.loads((sim / "clocks_truth.json").read_text())["videos"]}
    for k, video in enumerate(cameras.videos):
        video.clock_offset = truth[video.name] + 3.0 + (moved if k == 1 else 0.0)  # any common origin
    return cameras


def error_mm(solved: Reconstruction, points: np.ndarray, sim: Path) -> float:
    truth = truth_array(solved.problem, read_points(sim / "truth.csv"))
    distance = np.linalg.norm(points - truth, axis=-1)
    return float(np.nanmedian(distance[solved.problem.observed]))


def measures(entry: dict) -> str:
    key = "heldout_px" if entry.get("criterion") == "heldout_px" else "residual_px"
    values = entry.get(key) or {}
    if not values:
        return ""
    return f"{key} {values.get('solve', float('nan')):.3g} / {values.get('registered', float('nan')):.3g}"


def solve_wrong(name: str, sim: Path) -> list[str]:
    cameras = cameras_with(sim, 0.0)
    options = SolveOptions(recording=None)
    good = solve(cameras, sim / "tracks.csv", options)
    problem, rows = good.problem, []
    moved = problem.video_index == 1
    for shift in SOLVE_SHIFTS:
        clocks = copy.deepcopy(good.temporal.clocks)
        clocks.global_time[moved] += shift
        clocks.video(problem.video_names[1]).offset += shift
        start = good.seed.points if good.seed.stages else good.temporal.points
        fitted = refine(problem, start, clocks.global_time, options.temporal.refine)
        wrong = Temporal(clocks=clocks, points=fitted.points, times=clocks.global_time.copy(), refined=True, report={})
        check = check_registered_clocks(cameras, wrong.clocks)
        chosen = prefer_registered_offsets(problem, cameras, good.seed, wrong, check, options.temporal.refine)
        entry = chosen.report.get(PATH, {})
        rows.append(
            f"| {name} | solve's clock {shift:+.2f} s | {entry.get('criterion')} | {measures(entry)} | "
            f"{entry.get('kept')} | {error_mm(good, chosen.points, sim):.1f} (wrong clock "
            f"{error_mm(good, wrong.points, sim):.1f}, true {error_mm(good, good.temporal.points, sim):.1f}) |"
        )
        print(rows[-1], flush=True)
    return rows


def registration_wrong(name: str, sim: Path) -> list[str]:
    rows = []
    for shift in REGISTERED_SHIFTS:
        solved = solve(cameras_with(sim, shift), sim / "tracks.csv", SolveOptions(recording=None))
        entry = solved.temporal.report.get(PATH, {})
        rows.append(
            f"| {name} | registered offset {shift:+.2f} s | {entry.get('criterion', 'agree: not tried')} | "
            f"{measures(entry)} | {entry.get('kept', 'solve')} | {error_mm(solved, solved.temporal.points, sim):.1f} |"
        )
        print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/clock_choice"))
    parser.add_argument("--captures", default=",".join(CAPTURES))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    names = [n for n in args.captures.split(",") if n]
    if any(n not in CAPTURES for n in names):
        raise SystemExit(f"--captures: choose among {', '.join(CAPTURES)}")
    if any(n.startswith(("cmu", "hand", "two")) for n in names) and not CMU.exists():
        raise SystemExit(f"needs {CMU} (../shared): not found")
    args.work.mkdir(parents=True, exist_ok=True)
    print("| capture | case | criterion | solve / registered | kept | median error mm |")
    print("|---|---|---|---|---|---|")
    for name in names:
        sim = capture(name, args.work)
        solve_wrong(name, sim)
        registration_wrong(name, sim)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
