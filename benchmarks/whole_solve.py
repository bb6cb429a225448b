"""The whole `dynrecon solve` process by stage: wall time of the command (a subprocess, so imports and file reading
count), and the stage table of its report.json `timings` (reading inputs, rays, initialization, W-steps, X-steps,
clocks, refinement, trust, outputs, writing, recording).

    python benchmarks/whole_solve.py [--runs 3] [--sizes 700,2000] [--long] [--cases DIR] [--roots A,B] [--json OUT]

Data: `dynrecon simulate --mode phones` (4 videos on their own clocks, decoder times in cameras.json) on CMU 01_01
(P = 41) and complexknee 2022_01_0401 (P = 39-40 once the simulator drops the markers with gaps), cut to about F
frames; the table's P column is the report's. `--long` adds F = 20,000 (about
144 s of motion), longer than either file (23 and 34 s): the case folder then gets `palindrome.trc`, the file
played forward, backward, forward... up to the length needed, which the simulator reads instead. A palindrome keeps
every marker trajectory continuous (each turn reverses the velocity, like a bounce, never a jump). It also repeats
every pose exactly, once per pass, which no real take does and which gives the self-expressive solve near-duplicate
shapes far apart in time: so the whole take also turns slowly about the vertical axis through its centroid
(`--long-turns`, default one full turn over the take, a few degrees per second; 0 = the plain palindrome), and a
pose comes back rotated by tens of degrees. Its folder is named `<case>-<F>-palindrome[-turns<N>]`, so that a
capture cut at the file's end by an older version, or another take, is never reused for it.
Each case runs `--runs` times, the cases alternated so that a change of load on a shared machine spreads over all
of them; the table gives medians.
`--cases DIR` keeps the simulated captures there and reuses them on the next run; `--profile` writes a cProfile
of one solve of each case into DIR (or a temporary folder) and prints its top functions. `--roots` names source
trees to compare (e.g. an unchanged copy made with `git archive HEAD | tar -x -C DIR`, and this one): every run of a
case runs each tree in turn.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import pstats
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from reconstruct.outputs.mocap import read_mocap, write_trc  # noqa: E402
from simulation.simulate import vertical_axis  # noqa: E402

MOCAP = ROOT.parent / "shared" / "data" / "mocap"
# phones: 30 + 25 + 59.94 + 24 fps = 139 captures per second of motion, after start offsets of up to 0.5 s
CAPTURES_PER_S = 139.0
FILES = {"cmu P=41": ("cmu/cmu_01_01.c3d", 120.0), "complexknee P=40": ("lab/complexknee/2022_01_0401.c3d", 100.0)}
STAGES = [
    "read_inputs",
    "rays",
    "initialize",
    "w_step",
    "x_step",
    "total",
    "clocks",
    "refinement",
    "clocks_and_refinement",
    "trust",
    "outputs",
    "writing",
    "recording",
    "stage_total",
]


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def dynrecon(args: list[str], timeout: float, profile: Path | None = None, root: Path = ROOT) -> tuple[float, float]:
    """Runs `dynrecon ARGS` in a subprocess: (wall s, CPU s of the process, all its threads)."""
    start, cpu = time.perf_counter(), _children_cpu()
    prefix = ["-m", "cProfile", "-o", str(profile)] if profile else []
    subprocess.run([sys.executable, *prefix, "-m", "dynrecon", "-q", *args], check=True, timeout=timeout, cwd=root)
    return time.perf_counter() - start, _children_cpu() - cpu


def length_of(frames: int, rate: float) -> int:
    """Mocap samples (at `rate` Hz) that the phones turn into about `frames` captures."""
    return round((frames / CAPTURES_PER_S + 0.25) * rate)


def palindrome_index(samples: int, length: int) -> np.ndarray:
    """(length,) sample indices 0, 1, ..., samples - 1, samples - 2, ..., 0, 1, ...: forward, backward, forward."""
    period = 2 * (samples - 1)
    phase = np.arange(length) % period
    return np.where(phase < samples, phase, period - phase)


def turned(xyz: np.ndarray, turns: float) -> np.ndarray:
    """xyz (T, M, 3) turned about the vertical axis through its centroid by `turns` full turns over the T samples,
    at a constant rate (a rotation of the whole scene, so every trajectory stays continuous and smooth)."""
    up = int(np.argmax(vertical_axis(xyz)))
    a, b = [axis for axis in range(3) if axis != up]
    centre = np.nanmean(xyz.reshape(-1, 3), axis=0)
    angle = 2.0 * np.pi * turns * np.arange(len(xyz)) / len(xyz)
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    out = xyz.copy()
    da, db = xyz[..., a] - centre[a], xyz[..., b] - centre[b]
    out[..., a] = centre[a] + cos * da - sin * db
    out[..., b] = centre[b] + sin * da + cos * db
    return out


def write_palindrome(source: Path, length: int, path: Path, turns: float = 0.0) -> Path:
    """`length` samples of `source` played forward and backward in turn, turned by `turns` (`turned`), as a TRC
    file at the file's own rate.

    Each sample keeps its markers (NaN gaps included), so the simulator cleans the take as it cleans the file; the
    times are the file's first time plus k / rate, so they only grow.
    """
    mocap = read_mocap(source)
    if mocap.num_frames < 2:
        raise ValueError(f"{source}: a palindrome needs at least 2 samples")
    xyz = mocap.xyz[palindrome_index(mocap.num_frames, length)]
    times = mocap.times[0] + np.arange(length) / mocap.rate
    return write_trc(path, replace(mocap, xyz=turned(xyz, turns) if turns else xyz, times=times, path=path))


def case_folder(base: Path, name: str, file: str, rate: float, frames: int, turns: float) -> Path:
    """Where the case lives: `<name>-<F>`, or `<name>-<F>-palindrome[-turns<N>]` when the file is shorter."""
    folder = base / f"{name.split()[0]}-{frames}"
    if length_of(frames, rate) <= read_mocap(MOCAP / file).num_frames:
        return folder
    return folder.with_name(f"{folder.name}-palindrome" + (f"-turns{turns:g}" if turns else ""))


def simulate(folder: Path, file: str, rate: float, frames: int, turns: float) -> None:
    """Simulate the case into `folder` unless an earlier run left it there (a palindrome of the file if it is short)."""
    if (folder / "tracks.csv").exists():
        return
    length = length_of(frames, rate)
    mocap = MOCAP / file
    if "-palindrome" in folder.name:
        folder.mkdir(parents=True, exist_ok=True)
        mocap = write_palindrome(mocap, length, folder / "palindrome.trc", turns)
    sim = ["simulate", str(mocap), "--mode", "phones", "--cameras", "4", "--length", str(length)]
    dynrecon([*sim, "--out", str(folder)], 600)


def solve_command(folder: Path) -> list[str]:
    cameras, tracks, out = folder / "cameras.json", folder / "tracks.csv", folder / "out"
    return ["solve", "--cameras", str(cameras), "--tracks", str(tracks), "--out", str(out)]


def run_case(folder: Path, timeout: float, into: dict[str, list[float]], root: Path = ROOT) -> None:
    """One solve of the case by the source tree `root`; appends the process time and report.json's timings."""
    try:
        wall, cpu = dynrecon(solve_command(folder), timeout, root=root)
    except subprocess.TimeoutExpired:
        into.setdefault("process", []).append(float("inf"))
        return
    report = json.loads((folder / "out" / "report.json").read_text())
    into.setdefault("process", []).append(wall)
    into.setdefault("cpu", []).append(cpu)
    into.setdefault("F", []).append(report["size"]["frames"])
    into.setdefault("P", []).append(report["size"]["points"])
    for key, value in report["timings"].items():
        into.setdefault(key, []).append(value)


def profile_case(folder: Path, timeout: float, top: int) -> None:
    """One solve under cProfile; prints the functions with the most cumulative time."""
    path = folder / "solve.prof"
    dynrecon(solve_command(folder), timeout, profile=path)
    print(f"\n## cProfile of {folder.name}")
    pstats.Stats(str(path)).sort_stats("cumulative").print_stats(top)


def print_table(medians: dict[str, dict[str, float]]) -> None:
    shown = [s for s in STAGES if any(s in m for m in medians.values())]
    print(f"| case | F | P | process | process CPU | {' | '.join(shown)} |")
    print(f"|---|---|---|---|---|{'---|' * len(shown)}")
    for case, m in medians.items():
        cells = " | ".join(f"{m[s]:.2f}" if s in m else "" for s in shown)
        process, cpu = m.get("process", float("nan")), m.get("cpu", float("nan"))
        print(f"| {case} | {int(m.get('F', 0))} | {int(m.get('P', 0))} | {process:.1f} | {cpu:.1f} | {cells} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="700,2000", help="frames F, comma-separated")
    parser.add_argument("--long", action="store_true", help="also F = 20,000 (a palindrome of each file, see above)")
    parser.add_argument(
        "--long-turns", type=float, default=1.0, help="full turns of a palindrome take about the vertical (0: none)"
    )
    parser.add_argument("--runs", type=int, default=3, help="runs per case (median)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per solve")
    parser.add_argument("--cases", type=Path, help="keep the simulated captures here and reuse them")
    parser.add_argument("--only", default="", help="run only the cases whose name contains this")
    parser.add_argument("--profile", type=int, default=0, help="also profile one solve per case: top N functions")
    parser.add_argument("--roots", default="", help="source trees to compare, comma-separated (default: this one)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    roots = [Path(r).resolve() for r in args.roots.split(",") if r] or [ROOT]
    sizes = [int(s) for s in args.sizes.split(",")] + ([20_000] if args.long else [])
    with contextlib.ExitStack() as stack:
        base = args.cases or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        cases: dict[str, Path] = {}
        for name, (file, rate) in FILES.items():
            for frames in sizes:
                case = f"{name}, F~{frames}"
                if args.only in case:
                    cases[case] = case_folder(base, name, file, rate, frames, args.long_turns)
                    simulate(cases[case], file, rate, frames, args.long_turns)
        results: dict[str, dict[str, list[float]]] = {}
        for _ in range(args.runs):
            for case, folder in cases.items():
                for root in roots:
                    label = case if len(roots) == 1 else f"{case} [{root.name}]"
                    run_case(folder, args.timeout, results.setdefault(label, {}), root)
        for folder in cases.values() if args.profile else []:
            profile_case(folder, args.timeout, args.profile)
    medians = {case: {k: statistics.median(v) for k, v in r.items()} for case, r in results.items()}
    print_table(medians)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
