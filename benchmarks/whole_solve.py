"""The whole `dynrecon solve` process by stage: wall time of the command (a subprocess, so imports and file reading
count), and the stage table of its report.json `timings` (reading inputs, rays, initialization, W-steps, X-steps,
clocks and refinement, trust, writing, recording).

    python benchmarks/whole_solve.py [--runs 3] [--sizes 700,2000] [--long] [--json OUT]

Data: `dynrecon simulate --mode phones` (4 videos on their own clocks, decoder times in cameras.json) on CMU 01_01
(P = 41) and complexknee 2022_01_0401 (P = 20), cut to about F frames. Each case runs `--runs` times, the cases
alternated so that a change of load on a shared machine spreads over all of them; the table gives medians.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MOCAP = ROOT.parent / "shared" / "data" / "mocap"
# phones: 30 + 25 + 59.94 + 24 fps = 139 captures per second of motion, after start offsets of up to 0.5 s
CAPTURES_PER_S = 139.0
FILES = {"cmu P=41": ("cmu/cmu_01_01.c3d", 120.0), "complexknee P=20": ("lab/complexknee/2022_01_0401.c3d", 100.0)}
STAGES = [
    "read_inputs",
    "rays",
    "initialize",
    "w_step",
    "x_step",
    "clocks",
    "refinement",
    "clocks_and_refinement",
    "trust",
    "writing",
    "recording",
    "stage_total",
]


def dynrecon(args: list[str], timeout: float) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "dynrecon", "-q", *args], check=True, timeout=timeout, cwd=ROOT)
    return time.perf_counter() - start


def simulate(folder: Path, file: str, rate: float, frames: int) -> int:
    length = round((frames / CAPTURES_PER_S + 0.25) * rate)
    sim = ["simulate", str(MOCAP / file), "--mode", "phones", "--cameras", "4", "--length", str(length)]
    dynrecon([*sim, "--out", str(folder)], 600)
    return length


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="700,2000", help="frames F, comma-separated")
    parser.add_argument(
        "--long", action="store_true", help="also F = 20,000 (longer than the shared files: each is cut at its end)"
    )
    parser.add_argument("--runs", type=int, default=3, help="runs per case (median)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per solve")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")] + ([20_000] if args.long else [])
    with tempfile.TemporaryDirectory() as tmp:
        cases: dict[str, Path] = {}
        for name, (file, rate) in FILES.items():
            for frames in sizes:
                folder = Path(tmp) / f"{name.split()[0]}-{frames}"
                simulate(folder, file, rate, frames)
                cases[f"{name}, F~{frames}"] = folder
        results: dict[str, dict[str, list[float]]] = {case: {} for case in cases}
        for _ in range(args.runs):
            for case, folder in cases.items():
                out = folder / "out"
                cmd = ["solve", "--cameras", str(folder / "cameras.json"), "--tracks", str(folder / "tracks.csv")]
                try:
                    wall = dynrecon([*cmd, "--out", str(out)], args.timeout)
                except subprocess.TimeoutExpired:
                    results[case].setdefault("process", []).append(float("inf"))
                    continue
                report = json.loads((out / "report.json").read_text())
                results[case].setdefault("process", []).append(wall)
                results[case].setdefault("F", []).append(report["size"]["frames"])
                for key, value in report["timings"].items():
                    results[case].setdefault(key, []).append(value)
    medians = {case: {k: statistics.median(v) for k, v in r.items()} for case, r in results.items()}
    shown = [s for s in STAGES if any(s in m for m in medians.values())]
    print(f"| case | F | process | {' | '.join(shown)} |")
    print(f"|---|---|---|{'---|' * len(shown)}")
    for case, m in medians.items():
        cells = " | ".join(f"{m[s]:.2f}" if s in m else "" for s in shown)
        print(f"| {case} | {int(m.get('F', 0))} | {m['process']:.1f} | {cells} |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
