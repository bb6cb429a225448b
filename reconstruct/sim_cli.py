"""Subcommands `simulate` (the paper's protocol on a mocap file) and `evaluate` (accuracy vs truth.csv)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from reconstruct import evaluate as evaluate_module
from reconstruct import simulate as simulate_module


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    defaults = simulate_module.SimulationOptions()
    sim = subparsers.add_parser(
        "simulate", help="simulate unsynchronized cameras watching a motion-capture file",
        description="The seed paper's protocol: static virtual cameras (1000x1000 px, f = 1000) around "
                    "the motion; each mocap sample is seen by one camera. Writes cameras.json, tracks.csv, "
                    "truth.csv and simulation.json (units: mm).")
    sim.add_argument("mocap", type=Path, help="a .c3d or .trc motion-capture file")
    sim.add_argument("--out", type=Path, required=True, help="output folder")
    sim.add_argument("--cameras", type=int, default=defaults.cameras,
                     help="number of cameras (default %(default)s)")
    sim.add_argument("--step", type=int, default=defaults.step,
                     help="keep every STEP-th mocap sample (120 Hz mocap, 4 cameras: 1 = 30 Hz per camera)")
    sim.add_argument("--noise", type=float, default=defaults.noise_px, metavar="PX",
                     help="Gaussian pixel noise sigma (default %(default)s)")
    sim.add_argument("--miss", type=float, default=defaults.miss, metavar="FRAC",
                     help="fraction of observations removed at random (default %(default)s)")
    sim.add_argument("--unconstrained", action="store_true",
                     help="allow a camera to take two consecutive captures")
    sim.add_argument("--seed", type=int, default=defaults.seed, help="random seed (default %(default)s)")
    sim.add_argument("--start", type=int, default=defaults.start, help="first mocap frame (default 0)")
    sim.add_argument("--length", type=int, default=defaults.length,
                     help="window length in mocap frames, before --step (default: to the end)")
    sim.add_argument("--distance", type=float, default=None, metavar="MM",
                     help="fixed camera distance to the motion's centroid in mm (the paper averages 2700); default: "
                          "twice the motion's extent, moved back until every point is inside the images")
    sim.set_defaults(func=_simulate)

    ev = subparsers.add_parser(
        "evaluate", help="share of reconstructed points within 10..100 mm of the truth",
        description="Compare DIR/points3d.csv with DIR/truth.csv row by row (video, frame, point).")
    ev.add_argument("dir", type=Path, help="folder with points3d.csv (and truth.csv unless --truth)")
    ev.add_argument("--truth", type=Path, default=None, help="truth.csv of the simulation")
    ev.add_argument("--json", action="store_true", help="print the numbers as JSON instead of a table")
    ev.set_defaults(func=_evaluate)


def _simulate(args: argparse.Namespace) -> int:
    options = simulate_module.SimulationOptions(
        cameras=args.cameras, step=args.step, noise_px=args.noise, miss=args.miss,
        unconstrained=args.unconstrained, seed=args.seed, start=args.start, length=args.length,
        camera_distance_mm=args.distance)
    out = simulate_module.run(args.mocap, args.out, options)
    record = json.loads((out / "simulation.json").read_text(encoding="utf-8"))
    distance_m = record["camera_distance_mm"] / 1000
    summary = (f"{out}: {record['captures']} captures of {len(record['points'])} points in {options.cameras} "
               f"cameras at {distance_m:.2f} m, {record['observations']} observations")
    print(summary)  # noqa: T201
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    accuracy = evaluate_module.run(args.dir, args.truth)
    print(json.dumps(accuracy.as_dict()) if args.json else accuracy.table())  # noqa: T201
    return 0
