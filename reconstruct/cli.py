"""The `dynrecon solve` subcommand: cameras.json + tracks.csv in, 3D points out (`reconstruct.stage.run`).

Its defaults come from the solver's options, which load numpy and scipy: `dynrecon` builds this parser only when
`solve` is chosen (`COMMANDS`), and the stage loads in the handler.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

from dynrecon.arguments import out_path

log = logging.getLogger(__name__)

COMMANDS = {"solve": "reconstruct 3D points from cameras.json + tracks.csv (no synchronization needed)"}


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    from reconstruct.clocks.model import ClockModel
    from reconstruct.solver.alternation import SolverOptions
    from reconstruct.solver.xstep import RayConstraint
    from reconstruct.temporal import Refinement
    from reconstruct.trust import TrustPreset

    parser = subparsers.add_parser(
        "solve",
        help=COMMANDS["solve"],
        description="Self-expressive reconstruction (Zheng et al.): writes points3d.csv, sequencing.json, "
        "report.json and recording.rrd into OUT.",
    )
    parser.add_argument("--cameras", type=Path, required=True, help="cameras.json (per-frame poses)")
    parser.add_argument("--tracks", type=Path, required=True, help="tracks.csv (2D observations)")
    parser.add_argument("--out", type=out_path, required=True, help="output folder")
    defaults = SolverOptions()
    parser.add_argument("--lambda1", type=float, default=defaults.lambda1, help="structural coherence weight")
    parser.add_argument(
        "--lambda2",
        type=float,
        default=defaults.lambda2,
        help="smoothness weight of the first stage (0 skips that stage)",
    )
    parser.add_argument("--lambda3", type=float, default=defaults.lambda3, help="soft ray constraint weight")
    parser.add_argument(
        "--constraint",
        choices=[c.value for c in RayConstraint],
        default=defaults.constraint.value,
        help="points exactly on their rays (hard) or pulled to them (soft, for noisy tracks)",
    )
    parser.add_argument("--max-iterations", type=int, default=defaults.max_iterations, help="alternations per stage")
    parser.add_argument(
        "--refinement",
        choices=[r.value for r in Refinement],
        default=Refinement.CLOCKS.value,
        help="after the self-expressive solve: recover the video clocks and refine each trajectory on "
        "them (clocks, default), or keep the paper's solve (none)",
    )
    parser.add_argument(
        "--clock-model",
        choices=["auto", *(m.value for m in ClockModel)],
        default="auto",
        help="per-video clock: offset only, offset and rate, or with drift (auto: offset when every "
        "frame has a decoder time; for videos at a rate given (register --fps), offset unless the tracks show one "
        "running off it; else affine)",
    )
    parser.add_argument(
        "--trust",
        choices=[t.value for t in TrustPreset],
        default=TrustPreset.SENSITIVE.value,
        help=(
            "operating point of the trust flag in points3d.csv (limits in multiples of the capture's own "
            "medians; sensitive flags more, misses less)"
        ),
    )
    parser.add_argument(
        "--skeleton",
        type=Path,
        help='JSON {"connections": [["a", "b"], ...]}: bones drawn in the '
        "recording (the labeling page's skeleton file)",
    )
    parser.add_argument(
        "--videos",
        type=_names,
        nargs="+",
        default=[],
        metavar="NAME",
        help="solve only these videos of the cameras file, by name, separated by spaces or commas (default: all); "
        "e.g. one of the groups of videos that share no tracked point",
    )
    parser.add_argument("--no-recording", action="store_true", help="skip recording.rrd")
    parser.set_defaults(func=_solve)


def _names(text: str) -> tuple[str, ...]:
    """One `--videos` value: a name or names separated by commas (the other commands' `--videos` take several
    values, so `--videos cam0 cam1` and `--videos cam0,cam1` both work)."""
    names = tuple(name.strip() for name in text.split(","))
    if not any(names):
        raise argparse.ArgumentTypeError(f"{text!r} names no video")
    return tuple(name for name in names if name)


def _distinct_videos(values: list[tuple[str, ...]]) -> tuple[str, ...]:
    from dynrecon.errors import InputError

    names = tuple(name for value in values for name in value)
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise InputError(None, f"--videos names {', '.join(twice)} twice: give each video once")
    return names


def _solve(args: argparse.Namespace) -> int:
    from dynrecon.errors import InputError
    from labeling.skeleton import read_skeleton
    from reconstruct.clocks.model import ClockModel
    from reconstruct.solver.alternation import MAX_WEIGHT, SolverOptions
    from reconstruct.solver.xstep import RayConstraint
    from reconstruct.stage import SolveOptions, run
    from reconstruct.temporal import Refinement, TemporalOptions
    from reconstruct.trust import TrustPreset, preset_options

    if args.max_iterations < 1:
        raise InputError(None, f"--max-iterations {args.max_iterations} must be at least 1")
    for flag, value in (("--lambda1", args.lambda1), ("--lambda2", args.lambda2), ("--lambda3", args.lambda3)):
        if not (math.isfinite(value) and 0 <= value <= MAX_WEIGHT):  # argparse's float() takes nan, inf, negatives
            raise InputError(None, f"{flag} {value} must be a number from 0 to {MAX_WEIGHT:g}")
    if args.lambda3 == 0 and args.constraint == RayConstraint.SOFT.value:
        raise InputError(  # with no pull to their rays the points are free: any shape fits
            None,
            "--lambda3 0 with --constraint soft ties the points to no ray: give --lambda3 > 0 or --constraint hard",
        )
    solver = SolverOptions(
        lambda1=args.lambda1,
        lambda2=args.lambda2,
        lambda3=args.lambda3,
        constraint=RayConstraint(args.constraint),
        max_iterations=args.max_iterations,
        progress=True,
    )
    skeleton = tuple(read_skeleton(args.skeleton).connections) if args.skeleton else ()
    model = None if args.clock_model == "auto" else ClockModel(args.clock_model)
    temporal = TemporalOptions(clock_model=model, refinement=Refinement(args.refinement))
    points = run(
        args.cameras,
        args.tracks,
        args.out,
        SolveOptions(
            solver=solver,
            temporal=temporal,
            trust=preset_options(TrustPreset(args.trust)),
            recording=None if args.no_recording else SolveOptions().recording,
            skeleton=skeleton,
            videos=_distinct_videos(args.videos),
        ),
    )
    stale = args.out / "recording.rrd"
    if args.no_recording and stale.is_file():  # an earlier solve's, which would pass for this one's
        stale.unlink()
        log.info("removed the earlier solve's %s (--no-recording)", stale)
    print(  # noqa: T201
        f"wrote {points} (+ sequencing.json, report.json"
        + ("" if args.no_recording else ", recording.rrd: open with `rerun " + str(args.out / "recording.rrd") + "`")
        + ")"
    )
    return 0
