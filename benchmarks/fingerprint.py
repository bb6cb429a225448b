"""Regression fingerprint of whole solves, through the CLI only, so that it survives any reorganisation of the code.

Runs a fixed set of `dynrecon simulate` + `dynrecon solve` cases (paper protocol, noisy with missing data, phones
with decoder times, the paper's protocol without any time, a single point in flight) and the simulated demo, then
prints per case the share of points within 10 / 30 mm of the truth and a digest of `points3d.csv` and
`sequencing.json`. Solves are deterministic, so equal digests before and after a change mean equal results.

    python benchmarks/fingerprint.py --json /tmp/before.json
    python benchmarks/fingerprint.py --json /tmp/after.json --compare /tmp/before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MOCAP = ROOT.parent / "shared" / "data" / "mocap"

# name: (simulate arguments, solve arguments)
CASES: dict[str, tuple[list[str], list[str]]] = {
    "paper-cmu": ([str(MOCAP / "cmu/cmu_01_01.c3d"), "--start", "600", "--length", "300"], []),
    "paper-hdm05-noise1-miss20": (
        [str(MOCAP / "hdm05/HDM_dg_06-03_03_120.c3d"), "--noise", "1", "--miss", "0.2", "--seed", "3"],
        ["--constraint", "soft"],
    ),
    "paper-cmu-seed-only": (
        [str(MOCAP / "cmu/cmu_01_01.c3d"), "--start", "1800", "--length", "240"],
        ["--refinement", "none"],
    ),
    "phones-cmu": (
        [str(MOCAP / "cmu/cmu_01_01.c3d"), "--mode", "phones", "--start", "600", "--length", "300", "--seed", "1"],
        [],
    ),
    "flight-2s": (["--mode", "flight", "--duration", "2", "--seed", "2"], ["--refinement", "none"]),
}


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.exists() else "missing"


def run(cmd: list[str], timeout: float) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "dynrecon", "-q", *cmd], check=True, timeout=timeout, cwd=ROOT)
    return time.perf_counter() - start


def score(folder: Path) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-m", "dynrecon", "evaluate", str(folder), "--json"],
        check=True,
        capture_output=True,
        text=True,
        cwd=ROOT,
    ).stdout
    numbers = json.loads(out)
    return {
        "within_10mm": round(numbers["share_under"][0], 6),
        "within_30mm": round(numbers["share_under"][2], 6),
        "median_mm": round(numbers["median"], 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--compare", type=Path, help="an earlier --json to compare the digests with")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per solve")
    args = parser.parse_args()
    results: dict[str, dict[str, object]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (sim_args, solve_args) in CASES.items():
            folder = Path(tmp) / name
            run(["simulate", "--out", str(folder), *sim_args], args.timeout)
            seconds = run(
                [
                    "solve",
                    "--cameras",
                    str(folder / "cameras.json"),
                    "--tracks",
                    str(folder / "tracks.csv"),
                    "--out",
                    str(folder),
                    "--no-recording",
                    *solve_args,
                ],
                args.timeout,
            )
            results[name] = {
                "points": digest(folder / "points3d.csv"),
                "sequencing": digest(folder / "sequencing.json"),
                "scores": score(folder),
                "seconds": round(seconds, 1),
            }
            print(name, json.dumps(results[name]), flush=True)
        demo = Path(tmp) / "demo"
        seconds = run(["demo", "--simulated", "--out", str(demo)], args.timeout)
        found = sorted(demo.rglob("points3d.csv"))
        results["demo-simulated"] = {"points": digest(found[0]) if found else "missing", "seconds": round(seconds, 1)}
        print("demo-simulated", json.dumps(results["demo-simulated"]), flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    print(
        "\n| case | points digest | sequencing digest | within 10 mm | s |"
        + (" same as before |" if args.compare else "")
    )
    print("|---|---|---|---|---|" + ("---|" if args.compare else ""))
    before = json.loads(args.compare.read_text()) if args.compare else {}
    for name, row in results.items():
        scores = row.get("scores", {})
        within = scores.get("within_10mm", "") if isinstance(scores, dict) else ""
        same = ""
        if args.compare:
            old = before.get(name, {})
            same = (
                " yes |"
                if old.get("points") == row["points"] and old.get("sequencing") == row.get("sequencing")
                else " **no** |"
            )
        print(f"| {name} | {row['points']} | {row.get('sequencing', '')} | {within} | {row['seconds']} |{same}")


if __name__ == "__main__":
    main()
