"""`dynrecon demo`: the main job on the embedded sample, from a fresh clone, in a few minutes.

Until the video pipeline lands, the sample is a simulated capture: the procedural walker of `data_samples/` seen by
4 unsynchronized virtual cameras (30 Hz each, interleaved, never two at once), solved without any timing, scored
against the ground truth.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from dynrecon.errors import DynreconError
from labeling.workspace import read_skeleton
from reconstruct import evaluate, simulate
from reconstruct.solve_stage import SolveStageOptions
from reconstruct.solve_stage import run as solve_run

log = logging.getLogger(__name__)

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"


@dataclass(kw_only=True)
class DemoOptions:
    noise_px: float = 0.5  # a little pixel noise, as clicked or tracked points have
    seed: int = 0


def fresh_folder(base: Path) -> Path:
    """`base`, or `base-2`, `base-3`, ... : never write into a folder that already has results."""
    candidate, number = base, 1
    while candidate.exists() and any(candidate.iterdir()):
        number += 1
        candidate = base.with_name(f"{base.name}-{number}")
    candidate.mkdir(parents=True, exist_ok=True)
    return candidate


def run(out_dir: Path, options: DemoOptions | None = None) -> tuple[Path, evaluate.Accuracy]:
    options = options or DemoOptions()
    mocap = SAMPLES / "walker.trc"
    if not mocap.is_file():
        raise DynreconError(f"{mocap}: the embedded sample is missing (run `python data_samples/make_walker.py`)")
    out_dir = fresh_folder(out_dir)
    simulate.run(mocap, out_dir, simulate.SimulationOptions(noise_px=options.noise_px, seed=options.seed))
    skeleton = tuple(read_skeleton(SAMPLES / "walker_skeleton.json").connections)
    solve_run(out_dir / "cameras.json", out_dir / "tracks.csv", out_dir, SolveStageOptions(skeleton=skeleton))
    return out_dir, evaluate.run(out_dir)


def add_command(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the whole job on the embedded sample and score it",
                                   description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("dynrecon-demo"),
                        help="folder for the results (a fresh one is made beside it if it has results)")
    parser.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    out_dir, accuracy = run(args.out)
    print(f"demo: 4 unsynchronized cameras, walker sample, solved in {time.perf_counter() - started:.0f} s")  # noqa: T201
    print(f"accuracy vs ground truth (mm): {accuracy.table()}")  # noqa: T201
    print(f"results in {out_dir}; open the recording with: rerun {out_dir / 'recording.rrd'}")  # noqa: T201
    return 0
