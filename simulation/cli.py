"""Subcommands `simulate` (paper protocol, phones, or the flight scene) and `evaluate` (accuracy vs truth.csv).

The simulators' defaults load numpy and scipy: `dynrecon` builds these parsers only when one of `COMMANDS` is chosen,
and the simulators load in the handlers.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dynrecon.arguments import out_path
from dynrecon.errors import DynreconError

if TYPE_CHECKING:  # the simulators load numpy and scipy: only the type checker imports them here
    from simulation.flight import FlightOptions
    from simulation.phones import PhoneCaptureOptions
    from simulation.simulate import SimulationOptions

COMMANDS = {
    "simulate": "simulate unsynchronized cameras watching a motion-capture file (or a drone flight)",
    "evaluate": "share of reconstructed points within 10..100 mm of the truth",
}
MODES = ("paper", "phones", "flight")
# Options that only some modes read, by argparse dest; giving one to another mode is a mistake, not a no-op.
MODE_OPTIONS = {
    "step": ("paper",),
    "unconstrained": ("paper",),
    "times": ("paper",),
    "start": ("paper", "phones"),
    "length": ("paper", "phones"),
    "max_missing": ("paper", "phones"),
    "distance": ("paper", "phones"),
    "fps": ("phones", "flight"),
    "offsets": ("phones", "flight"),
    "drift_ppm": ("phones", "flight"),
    "jitter_ms": ("phones", "flight"),
    "vfr": ("phones", "flight"),
    "handheld": ("phones", "flight"),
    "shake_mm": ("phones", "flight"),
    "shake_deg": ("phones", "flight"),
    "false_fraction": ("phones", "flight"),
    "duration": ("flight",),
    "speed": ("flight",),
    "distance_m": ("flight",),
}
FLAG_OF = {"distance_m": "--distance-m", "false_fraction": "--false", "times": "--no-times"}


def _remember(namespace: argparse.Namespace, dest: str) -> None:
    given = getattr(namespace, "given", None)
    if given is None:
        given = set()
        namespace.given = given
    given.add(dest)


class _Given(argparse.Action):
    """Mixed into an argparse action: also note that the user gave the option (a mode's own defaults apply
    otherwise)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        super().__call__(parser, namespace, values, option_string)
        _remember(namespace, self.dest)


class _Store(_Given, argparse._StoreAction):
    pass


class _StoreTrue(_Given, argparse._StoreTrueAction):
    pass


class _StoreFalse(_Given, argparse._StoreFalseAction):
    pass


class _Boolean(_Given, argparse.BooleanOptionalAction):
    pass


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    _add_simulate(subparsers)
    _add_evaluate(subparsers)


def _add_simulate(subparsers: argparse._SubParsersAction) -> None:
    from simulation import flight as flight_module
    from simulation import phones as phone_capture
    from simulation import simulate as simulate_module

    defaults = simulate_module.SimulationOptions()
    phones = phone_capture.PhoneCaptureOptions()
    flight = flight_module.FlightOptions()
    sim = subparsers.add_parser(
        "simulate",
        help=COMMANDS["simulate"],
        description="--mode paper (default): the seed paper's protocol, static virtual cameras (1000x1000 px, "
        "f = 1000) around the motion, each mocap sample seen by one camera. --mode phones: each "
        "camera records on its own clock (own fps, start offset, optional drift and jitter), "
        "optionally handheld; truth interpolated at each capture time. --mode flight: one point on "
        "a drone's flight path, cameras 30-100 m away (no MOCAP). Writes cameras.json, tracks.csv, "
        "truth.csv, simulation.json (+ clocks_truth.json for phones and flight); units: mm.",
    )
    _add_capture_arguments(sim, defaults, flight)
    _add_phone_arguments(sim.add_argument_group("phones and flight"), phones, flight, phone_capture.DEFAULT_FPS)
    _add_flight_arguments(sim.add_argument_group("flight"), flight)
    sim.set_defaults(func=_simulate)


def _add_capture_arguments(sim: argparse.ArgumentParser, defaults: SimulationOptions, flight: FlightOptions) -> None:
    """Arguments every mode reads: input, output, mode and the paper-style capture settings."""
    sim.add_argument("mocap", type=Path, nargs="?", help="a .c3d or .trc motion-capture file (not for flight)")
    sim.add_argument("--out", type=out_path, required=True, help="output folder")
    sim.add_argument("--mode", choices=MODES, default="paper", help="capture model (default %(default)s)")
    sim.add_argument(
        "--cameras",
        type=int,
        default=defaults.cameras,
        action=_Store,
        help=f"number of cameras (default {defaults.cameras}; flight {flight.cameras})",
    )
    sim.add_argument(
        "--step",
        type=int,
        default=defaults.step,
        action=_Store,
        help="paper: keep every STEP-th mocap sample (120 Hz mocap, 4 cameras: 1 = 30 Hz per camera)",
    )
    sim.add_argument(
        "--noise",
        type=float,
        default=defaults.noise_px,
        metavar="PX",
        action=_Store,
        help=f"Gaussian pixel noise sigma (default {defaults.noise_px}; flight {flight.noise_px})",
    )
    sim.add_argument(
        "--miss",
        type=float,
        default=defaults.miss,
        metavar="FRAC",
        action=_Store,
        help="fraction of observations removed at random (default %(default)s)",
    )
    sim.add_argument(
        "--unconstrained", action=_StoreTrue, help="paper: allow a camera to take two consecutive captures"
    )
    sim.add_argument(
        "--no-times",
        dest="times",
        action=_StoreFalse,
        help="paper: cameras.json gives neither frame times nor fps (the paper's protocol as published)",
    )
    sim.add_argument("--seed", type=int, default=defaults.seed, action=_Store, help="random seed (default %(default)s)")
    sim.add_argument("--start", type=int, default=defaults.start, action=_Store, help="first mocap frame (default 0)")
    sim.add_argument(
        "--length",
        type=int,
        default=defaults.length,
        action=_Store,
        help="window length in mocap frames, before --step (default: to the end)",
    )
    sim.add_argument(
        "--max-missing",
        type=float,
        default=defaults.max_marker_missing,
        metavar="FRACTION",
        action=_Store,
        help="markers missing in more of the window's frames are left out, then frames missing a kept marker "
        "(default %(default)s)",
    )
    sim.add_argument(
        "--distance",
        type=float,
        default=None,
        metavar="MM",
        action=_Store,
        help="fixed camera distance to the motion's centroid in mm (the paper averages 2700); default: "
        "twice the motion's extent, moved back until every point is inside the images",
    )


def _add_phone_arguments(
    clocks: argparse._ArgumentGroup,
    phones: PhoneCaptureOptions,
    flight: FlightOptions,
    default_fps: Sequence[float],
) -> None:
    """The "phones and flight" group: per-camera clocks, handheld shake and false detections."""
    clocks.add_argument(
        "--fps",
        metavar="F1,F2,...",
        action=_Store,
        help=f"nominal frame rate of each camera (default: {','.join(f'{f:g}' for f in default_fps)}, cycled)",
    )
    clocks.add_argument(
        "--offsets",
        metavar="MIN,MAX",
        action=_Store,
        help="each camera starts at a time drawn uniformly in MIN..MAX s (default "
        f"{phones.offset_s[0]:g},{phones.offset_s[1]:g}; flight "
        f"{flight.offset_s[0]:g},{flight.offset_s[1]:g})",
    )
    clocks.add_argument(
        "--drift-ppm",
        type=float,
        metavar="PPM",
        action=_Store,
        help="clock rate errors drawn uniformly in +-PPM parts per million (default 0)",
    )
    clocks.add_argument(
        "--jitter-ms",
        type=float,
        metavar="MS",
        action=_Store,
        help="std of each frame's capture-time jitter (default 0)",
    )
    clocks.add_argument(
        "--vfr", action=_StoreTrue, help="cameras.json times carry the jitter (variable frame rate); default k / fps"
    )
    clocks.add_argument(
        "--handheld",
        action=_Boolean,
        help="shake the cameras (smooth random sway of centre and orientation); default off for phones, on for flight",
    )
    clocks.add_argument(
        "--shake-mm",
        type=float,
        metavar="MM",
        action=_Store,
        help=f"handheld: std of the centre's excursion per axis (default {phones.shake_mm:g}; "
        f"flight {flight.shake_mm:g})",
    )
    clocks.add_argument(
        "--shake-deg",
        type=float,
        metavar="DEG",
        action=_Store,
        help=f"handheld: std of the orientation's excursion per axis (default {phones.shake_deg:g}; "
        f"flight {flight.shake_deg:g})",
    )
    clocks.add_argument(
        "--false",
        dest="false_fraction",
        type=float,
        metavar="FRAC",
        action=_Store,
        help="share of detections replaced by a random pixel far from the truth (default 0; "
        f"flight {flight.false_fraction:g})",
    )


def _add_flight_arguments(scene: argparse._ArgumentGroup, flight: FlightOptions) -> None:
    """The "flight" group: the drone's path and the cameras' distance to it."""
    scene.add_argument(
        "--duration",
        type=float,
        metavar="S",
        action=_Store,
        help=f"length of the flight (default {flight.duration_s:g} s)",
    )
    scene.add_argument(
        "--speed",
        type=float,
        metavar="M/S",
        action=_Store,
        help=f"mean speed of the drone (default {flight.speed_mps:g} m/s)",
    )
    scene.add_argument(
        "--distance-m",
        metavar="MIN,MAX",
        action=_Store,
        help="horizontal camera distance to the path's centre, drawn in MIN..MAX m (default "
        f"{flight.distance_m[0]:g},{flight.distance_m[1]:g})",
    )


def _add_evaluate(subparsers: argparse._SubParsersAction) -> None:
    ev = subparsers.add_parser(
        "evaluate",
        help=COMMANDS["evaluate"],
        description="Compare DIR/points3d.csv with DIR/truth.csv row by row (video, frame, point).",
    )
    ev.add_argument("dir", type=Path, help="folder with points3d.csv (and truth.csv unless --truth)")
    ev.add_argument("--truth", type=Path, default=None, help="truth.csv of the simulation")
    ev.add_argument("--json", action="store_true", help="print the numbers as JSON instead of a table")
    ev.set_defaults(func=_evaluate)


def _numbers(text: str, flag: str, count: int | None = None) -> tuple[float, ...]:
    """Comma-separated numbers of a flag, or a one-line DynreconError."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise DynreconError(f"{flag} {text!r}: expected comma-separated numbers") from None
    if not all(math.isfinite(v) for v in values) or (count is not None and len(values) != count):
        raise DynreconError(f"{flag} {text!r}: expected {count or 'some'} finite comma-separated numbers")
    return values


def _pair(text: str, flag: str) -> tuple[float, float]:
    low, high = _numbers(text, flag, 2)
    return low, high


def _check_mode(args: argparse.Namespace) -> set[str]:
    given: set[str] = getattr(args, "given", None) or set()
    for dest in sorted(given):
        modes: Sequence[str] = MODE_OPTIONS.get(dest, MODES)
        if args.mode not in modes:
            flag = FLAG_OF.get(dest, "--" + dest.replace("_", "-"))
            raise DynreconError(f"{flag} does not apply to --mode {args.mode} (only to {', '.join(modes)})")
    if args.mode == "flight" and args.mocap is not None:
        raise DynreconError(f"--mode flight simulates its own scene: drop the MOCAP argument {args.mocap}")
    if args.mode != "flight" and args.mocap is None:
        raise DynreconError(f"--mode {args.mode} needs a MOCAP file (.c3d or .trc), or use --mode flight")
    if getattr(args, "distance", None) is not None and not (math.isfinite(args.distance) and args.distance > 0):
        raise DynreconError(f"--distance {args.distance}: give the cameras' distance in mm, above 0")
    if not 0 <= args.max_missing <= 1:
        raise DynreconError(f"--max-missing {args.max_missing}: give a fraction of the frames, 0 to 1")
    if args.seed < 0:  # numpy's generators take seeds >= 0 only
        raise DynreconError(f"--seed {args.seed}: give a whole number >= 0")
    return given


def _capture_fields(args: argparse.Namespace, given: set[str]) -> dict[str, Any]:
    """CaptureOptions fields the user gave (the mode's defaults fill the rest)."""
    from simulation.phones import Timestamps

    fields: dict[str, Any] = {}
    plain = {
        "cameras": "cameras",
        "noise": "noise_px",
        "miss": "miss",
        "seed": "seed",
        "drift_ppm": "drift_ppm",
        "jitter_ms": "jitter_ms",
        "handheld": "handheld",
        "shake_mm": "shake_mm",
        "shake_deg": "shake_deg",
        "false_fraction": "false_fraction",
        "start": "start",
        "length": "length",
        "max_missing": "max_marker_missing",
    }
    for dest, name in plain.items():
        if dest in given:
            fields[name] = getattr(args, dest)
    if "fps" in given:
        fields["fps"] = _numbers(args.fps, "--fps")
    if "offsets" in given:
        fields["offset_s"] = _pair(args.offsets, "--offsets")
    if args.vfr:
        fields["timestamps"] = Timestamps.VFR
    return fields


def _simulate(args: argparse.Namespace) -> int:
    from dynrecon.atomic import require_writable
    from simulation import flight as flight_module
    from simulation import phones as phone_capture
    from simulation import simulate as simulate_module

    given = _check_mode(args)
    require_writable(args.out)  # a traceback after the simulation otherwise
    if args.mode == "paper":
        options = simulate_module.SimulationOptions(
            cameras=args.cameras,
            step=args.step,
            noise_px=args.noise,
            miss=args.miss,
            unconstrained=args.unconstrained,
            times=args.times,
            seed=args.seed,
            start=args.start,
            length=args.length,
            camera_distance_mm=args.distance,
            max_marker_missing=args.max_missing,
        )
        out = simulate_module.run(args.mocap, args.out, options)
    elif args.mode == "phones":
        fields = _capture_fields(args, given)
        if "distance" in given:
            fields["camera_distance_mm"] = args.distance
        out = phone_capture.run(args.mocap, args.out, phone_capture.PhoneCaptureOptions(**fields))
    else:
        fields = {k: v for k, v in _capture_fields(args, given).items() if k not in ("start", "length")}
        if "duration" in given:
            fields["duration_s"] = args.duration
        if "speed" in given:
            fields["speed_mps"] = args.speed
        if "distance_m" in given:
            fields["distance_m"] = _pair(args.distance_m, "--distance-m")
        out = flight_module.run(args.out, flight_module.FlightOptions(**fields))
    record = json.loads((out / "simulation.json").read_text(encoding="utf-8"))
    cameras = record["options"]["cameras"]
    if args.mode in ("paper", "phones"):
        distance = record["camera_distance_mm"]
        # what a pixel of noise means there: at 15 m, 1 px is 15 mm and "within 10 mm" is out of reach
        where = f"at {distance / 1000:.2f} m (1 px ~ {distance / _focal_px(out):.2g} mm there)"
        if args.mode == "phones":
            where += ", " + ", ".join(f"{c['fps']:g}" for c in _clocks(out)) + " fps"
    else:
        rates = ", ".join(f"{c['fps']:g}" for c in _clocks(out))
        where = f"{rates} fps, {record['false_detections']} false detections"
    summary = (
        f"{out}: {record['captures']} captures of {len(record['points'])} points in {cameras} "
        f"cameras {where}, {record['observations']} observations"
    )
    print(summary)  # noqa: T201
    return 0


def _focal_px(out: Path) -> float:
    """The first camera's focal length (px) in the simulated cameras.json."""
    from sfm.cameras import read_cameras

    first = next(video for video in read_cameras(out / "cameras.json").videos if video.frames).frames[0]
    return float(first.K[0, 0])


def _clocks(out: Path) -> list[dict[str, Any]]:
    document = json.loads((out / "clocks_truth.json").read_text(encoding="utf-8"))
    return list(document["videos"])


def _evaluate(args: argparse.Namespace) -> int:
    from simulation import evaluate as evaluate_module

    accuracy = evaluate_module.run(args.dir, args.truth)
    print(json.dumps(accuracy.as_dict()) if args.json else accuracy.table())  # noqa: T201
    return 0
